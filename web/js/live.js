// Live push from the server (Server-Sent Events on GET /api/live, see server/console/live.py): machine
// states, throw progress, live throw samples, stored results, job progress, drift alerts, alarms, heartbeats,
// this console's changes.
// No polling: the page reacts to events. The server-unreachable banner (#server-banner) shows when
// the stream breaks or no heartbeat came for SILENT_MS, and hides again when events flow.
"use strict";

const Live = (() => {
  const SILENT_MS = 4000;
  const handlers = {};
  // the E-STOP still works for a day after a log-in expired (server.accounts.auth.STOP_GRACE_S)
  const LOGGED_OUT_TEXT = "This console's log-in has expired or ended: reload the page to log in again. Machine states " +
    "on this page are not live. The E-STOP still works for a day after a log-in expires.";
  let source = null, lastEventAt = 0, watchdog = null, connected = false, params = "", broke = true;
  let loggedOut = false; // the stream was refused and the server says this console's log-in is over

  function on(event, fn) { (handlers[event] = handlers[event] || []).push(fn); }

  function emit(event, data) { for (const fn of handlers[event] || []) fn(data); }

  /** Show the stream as up or down (``why``: the reason it is down). */
  function setConnected(ok, why) {
    if (ok) loggedOut = false;
    const banner = $("server-banner");
    if (banner) {
      banner.hidden = ok;
      if (!ok) {
        $("server-banner-title").textContent = loggedOut ? "LOGGED OUT." : "SERVER UNREACHABLE.";
        $("server-banner-text").textContent = loggedOut ? LOGGED_OUT_TEXT : `Server unreachable: ${why}. Machine states on this page are not live; reconnecting…`;
      }
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
      setConnected(false, "connection lost");
      if (source.readyState !== EventSource.CLOSED) return; // the browser reconnects by itself
      setTimeout(open, 2000); // refused (401/503) or the server gone: try again later
      // a refusal for the log-in would read as "server unreachable": ask, and say so until the stream is back
      fetch("/api/auth/me").then((r) => {
        if (r.status === 401 && !connected) { loggedOut = true; setConnected(false, "log-in ended"); }
      }).catch(() => {});
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

  return { on, start, isConnected: () => connected, isLoggedOut: () => loggedOut };
})();
