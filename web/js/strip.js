// The status strip of every console page (included after common.js and live.js): the selected
// machine's state with its reason, its active policies, the link to the server and the machine,
// the E-STOP button (Esc anywhere, the 3D frame included) and alarms that stay until acknowledged
// (a drift alarm is acknowledged on the server, which clears it on every open console).
// The strip is the first element of <body>, sticky at the top, so it never scrolls away. It owns
// the machine selection of every page (kept in localStorage, so every page shows the same machine):
// pages follow it with Strip.onSelect(fn) and read Strip.machines (machine_id -> live state).
"use strict";

const Strip = (() => {
  const STORE_MACHINE = "slinger.machine";
  const STORE_ALARMS = "slinger.alarms";
  const MAX_ALARMS = 20;
  const RESET_CONFIRM_MS = 10000;
  const MESSAGE_MS = 20000;
  const STATE_WORDS = { ready: "READY", not_ready: "NOT READY", throwing: "THROWING", estopped: "E-STOPPED", offline: "OFFLINE" };
  const machines = new Map();
  const selectHandlers = [];
  let machineId = null;
  let estopInFlight = null; // the E-STOP request on its way: presses while it flies join it
  let resetWait = null; // { machineId, timer } while a reset waits for the runtime's state
  let viserOrigin = null;

  const estopMarkup = `<button id="estop" class="estop" type="button" data-role="operator" aria-keyshortcuts="Escape"
      title="E-STOP: stop the selected machine now, valves to neutral (keyboard: Esc, anywhere on the page, the 3D view included)">E-STOP <kbd>Esc</kbd></button>`;
  const markup = `
    <div class="strip-row">
      <label class="machine-pick">Machine <select id="machine"></select></label>
      <span id="machine-kind" class="badge sim" hidden>SIMULATED</span>
      <span id="machine-state" class="state-badge state-unknown" role="status" aria-live="polite">connecting…</span>
      <span id="strip-reason" class="strip-reason"></span>
      <span id="strip-policy" class="strip-item"></span>
      <span id="strip-link" class="strip-item link-unknown">link: connecting…</span>
    </div>
    <div id="estop-banner" class="banner banner-estop" role="alert" hidden>
      <strong>E-STOPPED: <span id="estop-machine"></span> is latched, valves neutral.</strong> <span id="estop-text"></span>
      <button id="estop-reset" type="button" data-role="operator">Reset E-STOP…</button>
    </div>
    <p id="strip-msg" class="strip-msg" role="status" aria-live="assertive" hidden></p>
    <ul id="alarms" class="alarms" aria-label="alarms" hidden></ul>`;

  function mount() {
    const strip = document.createElement("div");
    strip.id = "strip";
    strip.className = "strip";
    strip.setAttribute("role", "region");
    strip.setAttribute("aria-label", "machine status and E-STOP");
    strip.innerHTML = markup;
    document.body.prepend(strip);
    // the E-STOP is a child of <body>, not of the strip: the sticky strip is a stacking context
    // below the dialogs' backdrop; on its own the button's z-index puts it above every dialog
    document.body.insertAdjacentHTML("afterbegin", estopMarkup);
  }

  // --- messages and alarms -------------------------------------------------------------------------
  let sayTimer = null;
  /** A message in the strip; one that is not an error goes away after MESSAGE_MS. */
  function say(text, kind = "") {
    const el = $("strip-msg");
    el.textContent = text;
    el.className = `strip-msg ${kind}`;
    el.hidden = !text;
    clearTimeout(sayTimer);
    if (text && kind !== "error") sayTimer = setTimeout(() => { el.hidden = true; }, MESSAGE_MS);
  }

  function loadAlarms() {
    try { return JSON.parse(localStorage.getItem(STORE_ALARMS) || "[]"); } catch (e) { return []; }
  }

  function saveAlarms(list) {
    try { localStorage.setItem(STORE_ALARMS, JSON.stringify(list.slice(-MAX_ALARMS))); } catch (e) { /* private mode */ }
  }

  function renderAlarms() {
    const list = loadAlarms();
    const ul = $("alarms");
    ul.innerHTML = "";
    ul.hidden = list.length === 0;
    for (const a of list.slice().reverse()) { // newest first: the one in view on a small screen
      const li = document.createElement("li");
      li.className = "alarm";
      li.dataset.key = a.key;
      const text = document.createElement("span");
      const head = document.createElement("strong");
      head.textContent = `ALARM ${new Date(a.at).toLocaleTimeString()}: ${a.title}`;
      const detail = document.createElement("span");
      detail.className = "alarm-detail";
      detail.textContent = ` ${a.text} `;
      text.append(head, detail, " ");
      const todo = document.createElement("em");
      todo.textContent = a.todo;
      text.append(todo);
      const ack = document.createElement("button");
      ack.type = "button";
      ack.className = "alarm-ack";
      ack.textContent = "Acknowledge";
      ack.setAttribute("aria-label", `Acknowledge alarm: ${a.title}`);
      ack.addEventListener("click", () => (a.drift ? acknowledgeDrift(a) : acknowledge(a.key)));
      li.append(text, ack);
      ul.append(li);
    }
  }

  /** Raise an alarm that stays (on every page, across reloads) until acknowledged; a second
   *  alarm with the same ``key`` replaces the first. ``extra`` is kept with it (``drift``: the
   *  machine whose drift alert the server acknowledges). */
  function raise(key, title, text, todo, extra = {}) {
    if (!$("strip-msg").classList.contains("error")) say(""); // an alarm outranks a passing message: keep the strip short
    const list = loadAlarms().filter((a) => a.key !== key);
    list.push({ key, title, text, todo, at: Date.now(), ...extra });
    saveAlarms(list);
    renderAlarms();
  }

  function acknowledge(key) {
    saveAlarms(loadAlarms().filter((a) => a.key !== key));
    renderAlarms();
  }

  /** A drift alarm is acknowledged on the server (audited): its ``drift`` event then clears the
   *  alarm on every open console, this one included. */
  async function acknowledgeDrift(a) {
    try {
      await api("POST", `/api/machines/${encodeURIComponent(a.drift)}/drift/ack`);
    } catch (e) {
      say(`Drift alert of ${a.drift} not acknowledged: ${sentence(e.message)}`, "error");
      return;
    }
    acknowledge(a.key);
    say(`Drift alert of ${a.drift} acknowledged.`, "ok");
  }

  /** The server's drift alert of a machine (server.drift; a ``drift`` event or a machine state's
   *  ``drift_alert``): an open one is an alarm until someone acknowledges it, on any console; an
   *  acknowledged one clears that alarm here. */
  function onDrift(alert) {
    if (!alert || !alert.machine_id) return;
    const mid = alert.machine_id;
    const key = `drift-${mid}-${alert.raised_at}`;
    const m = machines.get(mid);
    if (m) m.drift_alert = alert;
    const mine = loadAlarms().filter((a) => a.key.startsWith(`drift-${mid}-`));
    if (alert.status === "open") {
      if (!mine.some((a) => a.key === key)) {
        raise(key, `${mid}: accuracy drift`, alert.text || "The impacts drifted beyond what noise explains.",
          "A diagnosis of the recent throws was started: read it on the Diagnosis page before throwing on.", { drift: mid });
      }
    } else if (mine.length) {
      saveAlarms(loadAlarms().filter((a) => !a.key.startsWith(`drift-${mid}-`)));
      renderAlarms();
    }
  }

  /** What failed in a throw that did not land, in the operator's words: {what, text, todo}.
   *  ``what`` is "computer" (the control computer fell behind real time), "link" (the machine
   *  or its runtime stopped answering), "stop" (E-STOP or abort) or "machine". */
  function explainFailure(t) {
    const r = (t.failure_reason || "").toLowerCase();
    const sim = t.simulated ? "simulated " : "";
    if (r.includes("real time")) {
      return { what: "computer", text: `The ${sim}machine's control computer fell behind real time (${t.failure_reason}); the runtime stopped the swing and set the valves to neutral.`,
        todo: "Reduce the load on that computer, wait until the state is READY, then preview and throw again." };
    }
    if (r.includes("link") || r.includes("offline") || r.includes("restarted") || r.includes("no result") || r.includes("not running the throw")) {
      return { what: "link", text: `The link to ${t.machine_id} failed during the throw (${t.failure_reason}).`,
        todo: "Check the machine's network and that its runtime runs (Fleet page); preview again once it is READY." };
    }
    if (r.includes("e-stop") || r.includes("abort")) {
      return { what: "stop", text: `The throw was stopped (${t.failure_reason}).`,
        todo: "Reset the E-STOP when the area is safe, then preview again." };
    }
    return { what: "machine", text: `The machine ${t.machine_id} reported a fault (${t.failure_reason || "no reason given"}).`,
      todo: "Look at the machine; return it to the ready pose if offered, then preview again." };
  }

  async function onResult(ev) {
    let t;
    try { t = await api("GET", `/api/throws/${encodeURIComponent(ev.throw_id)}`); } catch (e) { return; }
    if (t.status === "landed") return;
    const m = machines.get(t.machine_id);
    const why = explainFailure({ ...t, simulated: m && m.simulated });
    const names = { computer: "the control computer", link: "the link", stop: "stopped", machine: "the machine" };
    raise(`throw-${t.id}`, `throw ${t.id.slice(0, 8)} on ${t.machine_id} ${t.status.toUpperCase()} (${names[why.what]})`, why.text, why.todo);
  }

  // --- machine state --------------------------------------------------------------------------------
  function render() {
    const m = machines.get(machineId);
    const badge = $("machine-state");
    const lost = !Live.isConnected();
    const link = $("strip-link");
    if (lost) {
      link.textContent = "link: server unreachable";
      link.className = "strip-item link-bad";
    } else if (m && m.state === "offline") {
      link.textContent = `link: ${m.machine_id} offline`;
      link.className = "strip-item link-bad";
    } else {
      link.textContent = "link: OK";
      link.className = "strip-item link-ok";
    }
    if (!m) {
      badge.textContent = lost ? "UNKNOWN: server unreachable" : "no machine";
      badge.className = "state-badge state-unknown";
      $("strip-reason").textContent = "";
      $("strip-policy").textContent = "";
      $("estop-banner").hidden = true;
      return;
    }
    const st = lost ? "unknown" : m.state;
    const words = lost ? "UNKNOWN (server unreachable)" : STATE_WORDS[m.state] || m.state;
    const phase = m.state === "throwing" && m.phase ? `: ${m.phase}` : "";
    badge.textContent = `${m.machine_id} ${words}${phase}`;
    badge.className = `state-badge state-${st}`;
    $("machine-kind").hidden = !m.simulated;
    const reason = !lost && m.state !== "ready" && m.reason ? m.reason : "";
    // a clock difference between the server and the machine's computer is compensated, but named
    $("strip-reason").textContent = [reason, !lost && m.clock_warning ? `Warning: ${m.clock_warning}.` : ""].filter(Boolean).join(" ");
    const pol = Object.entries(m.policies || {}).sort().map(([mode, v]) => `${mode} ${v}`).join(" · ");
    $("strip-policy").textContent = pol ? `policy ${pol}` : "no policy deployed";
    const banner = $("estop-banner");
    banner.hidden = m.state !== "estopped";
    $("estop-machine").textContent = m.machine_id;
    $("estop-text").textContent = m.estop_reason ? `Reason: ${m.estop_reason}. Throws are refused until Reset.` : "Throws are refused until Reset.";
    document.body.classList.toggle("estopped", m.state === "estopped");
    if (resetWait && resetWait.machineId === m.machine_id && m.state !== "estopped" && m.state !== "offline") {
      clearTimeout(resetWait.timer);
      resetWait = null;
      say(`E-STOP of ${m.machine_id} reset: confirmed by its runtime, the machine is ${words}.`, "ok");
    }
  }

  function renderList() {
    const sel = $("machine");
    const ids = [...machines.keys()].sort();
    if (sel.options.length !== ids.length || [...sel.options].some((o, i) => o.value !== ids[i])) {
      sel.innerHTML = "";
      for (const id of ids) sel.add(new Option(id, id));
    }
    for (const o of sel.options) {
      const m = machines.get(o.value);
      o.textContent = `${o.value} (${(STATE_WORDS[m.state] || m.state).toLowerCase()})`;
    }
    sel.value = machineId || "";
  }

  function onMachine(m) {
    const before = machines.get(m.machine_id);
    machines.set(m.machine_id, m);
    renderList();
    if (!machineId) {
      const stored = localStorage.getItem(STORE_MACHINE);
      select(stored && machines.has(stored) ? stored : m.machine_id);
    }
    if (before && before.state !== "offline" && m.state === "offline") {
      raise(`offline-${m.machine_id}`, `${m.machine_id} OFFLINE (the link)`, `The runtime of ${m.machine_id} stopped answering: ${m.reason || "offline"}.`,
        "Check the machine's computer and network; start its runtime again (slinger runtime).");
    }
    const drift = m.drift_alert;
    if (drift && (!before || !before.drift_alert || before.drift_alert.raised_at !== drift.raised_at || before.drift_alert.status !== drift.status)) onDrift(drift);
    if (m.machine_id === machineId) render();
  }

  /** Make ``id`` the selected machine of this page (and of the next page opened). */
  function select(id) {
    if (!id || id === machineId) return;
    machineId = id;
    try { localStorage.setItem(STORE_MACHINE, id); } catch (e) { /* private mode */ }
    renderList();
    render();
    for (const fn of selectHandlers) fn(id);
  }

  // --- E-STOP ---------------------------------------------------------------------------------------
  /** Stop the selected machine. Presses while a stop is on its way join that request. */
  function estop(source = "button") {
    if (estopInFlight) return estopInFlight;
    const mid = machineId;
    if (!mid) { say("E-STOP: no machine selected. Use the machine's own emergency stop.", "error"); return Promise.resolve(); }
    say(`E-STOP sent to ${mid}…`, "error");
    $("estop").setAttribute("aria-busy", "true");
    estopInFlight = api("POST", `/api/machines/${encodeURIComponent(mid)}/estop`, { reason: `E-STOP in the console (${source})` })
      .then((r) => {
        say(`E-STOP confirmed by the runtime of ${r.machine_id}: valves neutral` +
          (r.aborted_throw_id ? `, throw ${r.aborted_throw_id.slice(0, 8)} aborted` : "") + ".", "error");
      })
      .catch((e) => {
        say(`E-STOP NOT CONFIRMED for ${mid}: ${e.message} Use the machine's own emergency stop.`, "error");
        raise(`estop-${mid}`, `E-STOP of ${mid} NOT CONFIRMED (the link)`, e.message, "Use the machine's own emergency stop now.");
      })
      .finally(() => { estopInFlight = null; $("estop").removeAttribute("aria-busy"); });
    return estopInFlight;
  }

  async function resetEstop() {
    const mid = machineId;
    const ok = await confirmAction(`Reset the E-STOP of ${mid}?`, `${mid} accepts commands again after the reset. ` +
      "Only reset when the area around the machine is safe and the cause of the stop is dealt with.", "Reset E-STOP");
    if (!ok) { say(`E-STOP of ${mid} stays latched.`); return; }
    try {
      await api("POST", `/api/machines/${encodeURIComponent(mid)}/estop/reset`);
    } catch (e) {
      say(`Reset refused: ${e.message}`, "error");
      return;
    }
    const m = machines.get(mid);
    if (m && m.state !== "estopped") { say(`E-STOP of ${mid} reset: confirmed by its runtime, the machine is ${STATE_WORDS[m.state] || m.state}.`, "ok"); return; }
    say(`E-STOP of ${mid} reset sent; waiting for its runtime's state…`);
    if (resetWait) clearTimeout(resetWait.timer);
    resetWait = { machineId: mid, timer: setTimeout(() => {
      resetWait = null;
      say(`E-STOP of ${mid}: the reset was accepted but the runtime still reports E-STOPPED after ${RESET_CONFIRM_MS / 1000} s. Press Reset again or check the machine.`, "error");
    }, RESET_CONFIRM_MS) };
  }

  function isStopKey(e) { return e.key === "Escape" || e.key === "Esc"; }

  function onKey(e) {
    if (!isStopKey(e) || e.repeat) return;
    if (!can("operator")) return;
    e.preventDefault();
    estop("Esc key");
  }

  /** Esc pressed inside the 3D view (viser's page, another origin): that page posts
   *  {slinger: "estop"} to us (server.scene injects the listener). */
  function onFrameMessage(e) {
    if (!e.data || e.data.slinger !== "estop") return;
    if (viserOrigin && e.origin !== viserOrigin) return;
    if (!viserOrigin && !/^https?:\/\//.test(e.origin)) return;
    if (!can("operator")) return;
    estop("Esc key in the 3D view");
  }

  // --- start ----------------------------------------------------------------------------------------
  async function init() {
    if (!session.user) { try { await whoAmI(); } catch (e) { return; } }
    for (const el of [$("estop"), ...$("strip").querySelectorAll("[data-role]")]) el.hidden = !can(el.dataset.role);
    try {
      for (const m of await api("GET", "/api/machines")) {
        if (!machines.has(m.id)) machines.set(m.id, { machine_id: m.id, state: m.online ? "not_ready" : "offline",
          reason: m.online ? "waiting for live state" : "runtime offline", policies: m.policies, simulated: m.simulated });
      }
    } catch (e) { /* the live stream fills it */ }
    const stored = localStorage.getItem(STORE_MACHINE);
    const first = stored && machines.has(stored) ? stored : [...machines.keys()].sort()[0];
    renderList();
    if (first) select(first);
    render();
    if (!document.body.classList.contains("console-page")) Live.start(); // the console starts it with its console id
  }

  mount();
  renderAlarms();
  $("estop").addEventListener("click", () => estop("button"));
  $("estop-reset").addEventListener("click", resetEstop);
  $("machine").addEventListener("change", (e) => select(e.target.value));
  window.addEventListener("keydown", onKey, true); // capture: before any field or dialog sees it
  window.addEventListener("message", onFrameMessage);
  window.addEventListener("storage", (e) => { if (e.key === STORE_ALARMS) renderAlarms(); });
  Live.on("machine", onMachine);
  Live.on("result", onResult);
  Live.on("drift", onDrift);
  for (const ev of ["connected", "resumed", "disconnected"]) Live.on(ev, render);
  document.addEventListener("DOMContentLoaded", init);

  return {
    machines, estop, raise, acknowledge, select, say, explainFailure,
    get machineId() { return machineId; },
    onSelect: (fn) => selectHandlers.push(fn),
    setViserOrigin: (origin) => { viserOrigin = origin; },
    isEstopInFlight: () => !!estopInFlight,
  };
})();
