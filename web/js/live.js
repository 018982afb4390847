// Live push from the server (Server-Sent Events on GET /api/live, see server/console/live.py): machine
// states, throw progress, live throw samples, stored results, job progress, drift alerts, alarms, heartbeats,
// this console's changes.
// No polling: the page reacts to events. The server-unreachable banner (#server-banner) shows when
// the stream breaks or no heartbeat came for SILENT_MS, and hides again when events flow.
"use strict";

const Live = (() => {
  const SILENT_MS = 4000;
  const handlers = {};
  let source = null, lastEventAt = 0, watchdog = null, connected = false, params = "", broke = true;

  function on(event, fn) { (handlers[event] = handlers[event] || []).push(fn); }

  function emit(event, data) { for (const fn of handlers[event] || []) fn(data); }

  function setConnected(ok, why) {
    const banner = $("server-banner");
    if (banner) {
      banner.hidden = ok;
      if (!ok) $("server-banner-text").textContent = `Server unreachable: ${why}. Machine states on this page are not live; reconnecting…`;
    }
    document.body.classList.toggle("server-lost", !ok);
    if (ok !== connected) {
      connected = ok;
      // "connected" (refetch what may have been missed) only after the stream really broke;
      // a mere pause of the events (a slow server) resumes without any request
      if (ok && broke) { broke = false; emit("connected", {}); } else emit(ok ? "resumed" : "disconnected", { why });
    }
  }

  function listen(name) {
    source.addEventListener(name, (e) => {
      lastEventAt = Date.now();
      if (!connected) setConnected(true);
      let data = null;
      try { data = JSON.parse(e.data); } catch (err) { return; }
      emit(name, data);
    });
  }

  function open() {
    if (source) source.close();
    source = new EventSource(`/api/live${params}`);
    for (const name of ["machine", "throw", "sample", "result", "heartbeat", "console", "job", "drift", "alarm", "deployment"]) listen(name);
    source.addEventListener("open", () => { lastEventAt = Date.now(); setConnected(true); });
    source.addEventListener("error", () => {
      broke = true;
      if (source.readyState === EventSource.CLOSED) setTimeout(open, 2000); // e.g. 401/503: try again later
      setConnected(false, "connection lost");
    });
  }

  /** Start the stream (``consoleId``: also receive that console's own events); a second call
   *  with the same argument keeps the stream that runs. */
  function start(consoleId) {
    const wanted = consoleId ? `?console=${encodeURIComponent(consoleId)}` : "";
    if (source && wanted === params) return; // already streaming (the status strip and a page may both ask)
    params = wanted;
    lastEventAt = Date.now();
    open();
    clearInterval(watchdog);
    watchdog = setInterval(() => {
      if (Date.now() - lastEventAt > SILENT_MS) setConnected(false, `no word from it for ${Math.round((Date.now() - lastEventAt) / 1000)} s`);
    }, 500);
  }

  return { on, start, isConnected: () => connected };
})();
