// The status strip of every console page (included after common.js and live.js): the selected
// machine's state with its reason, its active policies, the link to the server and the machine,
// the E-STOP button (Esc anywhere, the 3D frame included; it acts on pointerdown) and the alarm
// banner. Alarms are kept on the server (server/console/alarms.py, GET /api/alarms, ``alarm`` events): an
// acknowledgement, an acknowledge-all or a shelving in one console shows in every console. The
// banner is one line (count, the most urgent alarm, Acknowledge all, Show all); the list it opens
// scrolls inside at most a sixth of the viewport, so it never pushes the page's controls away.
// Alarms this page alone knows (an E-STOP the server did not confirm) join the banner, marked local.
// The strip is the first element of <body>, sticky at the top, so it never scrolls away. It owns
// the machine selection of every page (kept in localStorage, so every page shows the same machine):
// pages follow it with Strip.onSelect(fn) and read Strip.machines (machine_id -> live state).
"use strict";

const Strip = (() => {
  const STORE_MACHINE = "slinger.machine";
  const PRIORITY_RANK = { high: 0, medium: 1, low: 2 };
  const SHELVE_MIN = 60;
  const RESET_CONFIRM_MS = 10000;
  const MESSAGE_MS = 20000;
  const STATE_WORDS = { ready: "READY", not_ready: "NOT READY", throwing: "THROWING", estopped: "E-STOPPED", offline: "OFFLINE" };
  const machines = new Map();
  const selectHandlers = [];
  let machineId = null;
  let estopInFlight = null; // the E-STOP request on its way: presses while it flies join it
  let resetWait = null; // { machineId, timer } while a reset waits for the runtime's state
  let viserOrigin = null;
  const alarms = new Map(); // alarm id -> the server's alarm (server.console.alarms.alarm_dict)
  const localAlarms = new Map(); // key -> {key, title, text, todo, at}: what only this page knows
  let alarmsOpen = false;
  let shelfTimer = null; // asks for the alarms again when the first shelving ends (renderAlarms)

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
    <section id="alarm-banner" class="alarm-banner" aria-label="alarms" hidden>
      <div class="alarm-head"><strong id="alarm-count" class="alarm-count"></strong>
        <span id="alarm-top" class="alarm-top"></span>
        <button id="alarm-ack-all" type="button" data-role="operator">Acknowledge all</button>
        <button id="alarm-toggle" type="button" aria-expanded="false" aria-controls="alarms">Show all</button>
        <a href="alarms.html">History</a></div>
      <ul id="alarms" class="alarms" aria-label="active alarms" hidden></ul>
    </section>`;

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

  /** The alarms the banner shows: active, not shelved, the page's own local ones included;
   *  unacknowledged first, then by priority, newest first. */
  function shownAlarms() {
    const list = [...alarms.values()].filter((a) => a.active && !a.shelved)
      .concat([...localAlarms.values()].map((a) => ({ ...a, id: a.key, local: true, state: "unacked",
        raised_at: new Date(a.at).toISOString() })));
    const unacked = (a) => (a.state === "unacked" || a.state === "rtn_unacked" ? 0 : 1);
    return list.sort((a, b) => unacked(a) - unacked(b) || PRIORITY_RANK[a.priority] - PRIORITY_RANK[b.priority] ||
      String(b.raised_at).localeCompare(String(a.raised_at)));
  }

  function alarmItem(a) {
    const li = document.createElement("li");
    li.className = `alarm alarm-${a.priority} alarm-${a.state}`;
    li.dataset.key = a.key;
    li.dataset.id = a.id;
    const head = document.createElement("strong");
    const when = new Date(a.raised_at).toLocaleTimeString();
    const status = { unacked: "", acked: " (acknowledged)", rtn_unacked: " (cleared, not acknowledged)" }[a.state] || "";
    head.textContent = `${a.priority.toUpperCase()} ${when}: ${a.title}${status}${a.local ? " (this page)" : ""}`;
    const detail = document.createElement("span");
    detail.className = "alarm-detail";
    detail.textContent = ` ${a.text} `;
    const todo = document.createElement("em");
    todo.textContent = a.todo;
    li.append(head, detail, todo, " ");
    if (a.state === "unacked" || a.state === "rtn_unacked") {
      const ack = document.createElement("button");
      ack.type = "button";
      ack.className = "alarm-ack";
      ack.textContent = "Acknowledge";
      ack.setAttribute("aria-label", `Acknowledge alarm: ${a.title}`);
      ack.addEventListener("click", () => acknowledge(a));
      li.append(ack, " ");
    }
    if (!a.local && can("operator")) {
      const shelve = document.createElement("button");
      shelve.type = "button";
      shelve.className = "alarm-shelve quiet";
      shelve.textContent = `Shelve ${SHELVE_MIN} min`;
      shelve.setAttribute("aria-label", `Shelve alarm for ${SHELVE_MIN} minutes: ${a.title}`);
      shelve.addEventListener("click", () => shelveAlarm(a));
      li.append(shelve);
    }
    return li;
  }

  function renderAlarms() {
    const list = shownAlarms();
    const banner = $("alarm-banner");
    banner.hidden = list.length === 0;
    const unacked = list.filter((a) => a.state === "unacked" || a.state === "rtn_unacked").length;
    const shelved = [...alarms.values()].filter((a) => a.active && a.shelved).length;
    $("alarm-count").textContent = `ALARMS ${list.length}` + (unacked ? ` (${unacked} unacknowledged)` : "") +
      (shelved ? ` · ${shelved} shelved` : "");
    $("alarm-top").textContent = list.length ? `${list[0].priority.toUpperCase()}: ${list[0].title}` : "";
    $("alarm-top").title = list.length ? `${list[0].text} ${list[0].todo}` : "";
    $("alarm-ack-all").disabled = unacked === 0;
    $("alarm-ack-all").hidden = !can("operator");
    const ul = $("alarms");
    ul.innerHTML = "";
    for (const a of list) ul.append(alarmItem(a));
    ul.hidden = !alarmsOpen || list.length === 0;
    $("alarm-toggle").textContent = alarmsOpen ? "Hide" : `Show all`;
    $("alarm-toggle").setAttribute("aria-expanded", String(alarmsOpen));
    // a shelving that runs out is no event: the banner asks again when the first one ends
    clearTimeout(shelfTimer);
    const wait = msToShelfEnd([...alarms.values()]);
    if (wait !== null) shelfTimer = setTimeout(loadAlarms, wait);
  }

  /** An alarm only this page knows (the server may be unreachable, e.g. an unconfirmed E-STOP):
   *  in the banner until acknowledged here; a second with the same ``key`` replaces the first.
   *  ``priority``: "high" (default), "medium" or "low", as the server's alarms. */
  function raise(key, title, text, todo, priority = "high") {
    if (!$("strip-msg").classList.contains("error")) say(""); // an alarm outranks a passing message: keep the strip short
    localAlarms.set(key, { key, title, text, todo, priority, at: Date.now() });
    renderAlarms();
  }

  // Alarms heard (events, answers to this page's acts) while GET /api/alarms is on its way: the
  // server may have answered before them, so they are applied again over its list.
  let heardWhileLoading = null;
  // Of two records of one alarm the one with the higher ``revision`` is newer (the server counts
  // every change of an alarm: server.db.models.Alarm.revision). A record older than the one the page
  // shows is an answer to this page's acknowledge or shelve that landed after the live event of a
  // later change: it is dropped. ``retired``: ids of alarms the page has seen leave the active list
  // (cleared and acknowledged, which is never undone).
  const retired = new Set();
  function isOlder(a, known) {
    return retired.has(a.id) || (known !== undefined && a.revision < known.revision);
  }

  function onAlarm(a) {
    if (!a || !a.id) return;
    if (heardWhileLoading) heardWhileLoading.push(a);
    if (isOlder(a, alarms.get(a.id))) return;
    if (a.active) alarms.set(a.id, a); else { alarms.delete(a.id); retired.add(a.id); }
    renderAlarms();
  }

  async function loadAlarms() {
    const heard = heardWhileLoading = [];
    try {
      const list = await api("GET", "/api/alarms");
      if (heardWhileLoading !== heard) return; // a newer load is on its way
      alarms.clear();
      for (const a of list) alarms.set(a.id, a);
      heardWhileLoading = null;
      for (const a of heard) onAlarm(a);
      renderAlarms();
    } catch (e) { /* the live stream brings them */ } finally { if (heardWhileLoading === heard) heardWhileLoading = null; }
  }

  /** Acknowledge one alarm (on the server: audited, every console follows; a local one here). */
  async function acknowledge(a) {
    if (a.local) { localAlarms.delete(a.key); renderAlarms(); return; }
    try {
      onAlarm(await api("POST", `/api/alarms/${encodeURIComponent(a.id)}/ack`));
    } catch (e) {
      say(`Alarm not acknowledged: ${sentence(e.message)}`, "error");
      return;
    }
    say(a.cause === "drift" ? `Drift alert of ${a.machine_id} acknowledged.` : `Alarm acknowledged: ${a.title}.`, "ok");
  }

  async function acknowledgeAll() {
    localAlarms.clear();
    try {
      const done = await api("POST", "/api/alarms/ack-all", {});
      for (const a of done) onAlarm(a);
      say(`${done.length} alarm${done.length === 1 ? "" : "s"} acknowledged.`, "ok");
    } catch (e) {
      say(`Alarms not acknowledged: ${sentence(e.message)}`, "error");
    }
    renderAlarms();
  }

  async function shelveAlarm(a) {
    try {
      onAlarm(await api("POST", `/api/alarms/${encodeURIComponent(a.id)}/shelve`, { minutes: SHELVE_MIN }));
      say(`Alarm shelved for ${SHELVE_MIN} minutes (listed on the Alarms page until then): ${a.title}.`, "ok");
    } catch (e) {
      say(`Alarm not shelved: ${sentence(e.message)}`, "error");
    }
  }

  /** What failed in a throw that did not land, in the operator's words: {what, text, todo}, by
   *  the same rules as the server's alarms (server.console.alarms.failure_cause). ``what`` is "computer"
   *  (the control computer fell behind real time: its load, not the network), "runtime" (the
   *  runtime did not answer), "link" (the link to the machine was lost), "stop" (the operator's
   *  E-STOP or abort) or "machine". */
  function explainFailure(t) {
    const r = (t.failure_reason || "").toLowerCase();
    const sim = t.simulated ? "simulated " : "";
    if (r.includes("e-stop") || r.includes("abort")) {
      return { what: "stop", text: `The throw was stopped (${t.failure_reason}).`,
        todo: "Reset the E-STOP when the area is safe, then preview again." };
    }
    if (r.includes("real time")) {
      return { what: "computer", text: `The ${sim}machine's control computer fell behind real time (${t.failure_reason}); the runtime stopped the swing and set the valves to neutral. This is the computer's load, not the network.`,
        todo: "Reduce the load on that computer, wait until the state is READY, then preview and throw again." };
    }
    if (["not answering", "no result", "restarted", "not running the throw", "runtime"].some((w) => r.includes(w))) {
      return { what: "runtime", text: `The runtime of ${t.machine_id} did not answer during the throw (${t.failure_reason}).`,
        todo: "Check on the Fleet page that its runtime runs; preview again once the machine is READY." };
    }
    if (r.includes("link") || r.includes("offline")) {
      return { what: "link", text: `The link between the runtime and the ${sim}machine ${t.machine_id} was lost during the throw (${t.failure_reason}).`,
        todo: "Check the machine's network and its computer's load; preview again once it is READY." };
    }
    return { what: "machine", text: `The machine ${t.machine_id} reported a fault (${t.failure_reason || "no reason given"}).`,
      todo: "Look at the machine; return it to the ready pose if offered, then preview again." };
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
    // keepPage: a console whose log-in the server no longer takes stays here and says so (a log-in
    // that merely expired still stops: server.accounts.auth.STOP_GRACE_S)
    estopInFlight = api("POST", `/api/machines/${encodeURIComponent(mid)}/estop`, { reason: `E-STOP in the console (${source})` },
      false, { keepPage: true })
      .then((r) => {
        say(`E-STOP confirmed by the runtime of ${r.machine_id}: valves neutral` +
          (r.aborted_throw_id ? `, throw ${r.aborted_throw_id.slice(0, 8)} aborted` : "") + "." +
          (r.login_expired_at ? ` Your log-in expired at ${new Date(r.login_expired_at).toLocaleTimeString()}: ` +
            "log in again before anything else (reload the page)." : ""), "error");
      })
      .catch((e) => {
        if (e.status === 401) {
          const why = "The server no longer takes this console's log-in (logged out, or the account was disabled or changed).";
          say(`E-STOP NOT SENT to ${mid}: ${why} Use the machine's own emergency stop now, then log in again.`, "error");
          raise(`estop-${mid}`, `E-STOP of ${mid} NOT SENT`, why, "Use the machine's own emergency stop now, then log in again (reload the page).");
          return;
        }
        say(`E-STOP NOT CONFIRMED for ${mid}: ${e.message} Use the machine's own emergency stop.`, "error");
        raise(`estop-${mid}`, `E-STOP of ${mid} NOT CONFIRMED`, e.message, "Use the machine's own emergency stop now.");
      })
      .finally(() => { estopInFlight = null; $("estop").removeAttribute("aria-busy"); });
    return estopInFlight;
  }

  async function resetEstop() {
    const mid = machineId;
    const ok = await confirmAction(`Reset the E-STOP of ${mid}?`, `${mid} accepts commands again after the reset. ` +
      "Only reset when the area around the machine is safe and the cause of the stop is dealt with.", "Reset E-STOP");
    if (!ok) { say(`E-STOP of ${mid} stays latched.`); return; }
    // A stop still on its way would reach the server after the reset and latch the machine again:
    // the reset follows every press made before it.
    while (estopInFlight) {
      say(`E-STOP of ${mid}: waiting for the stop on its way before the reset…`);
      await estopInFlight.catch(() => {});
    }
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

  // --- the end of the log-in ----------------------------------------------------------------------
  const LOGIN_NOTICE_MS = 15 * 60 * 1000; // how long before its end the log-in's end is announced
  let loginTimers = [];
  /** Announce the end of this page's log-in (``expiresAt``: ISO 8601 UTC, GET /api/auth/me) as an
   *  alarm of the page LOGIN_NOTICE_MS before it and when it comes: after it every command but the
   *  E-STOP asks for a new log-in, and the E-STOP still works for a day (server.accounts.auth.STOP_GRACE_S). */
  function watchLogIn(expiresAt) {
    for (const t of loginTimers) clearTimeout(t);
    const end = Date.parse(expiresAt);
    if (!Number.isFinite(end)) return;
    const at = new Date(end).toLocaleTimeString();
    const todo = "Log out and in again to keep commanding. The E-STOP keeps working for a day after the log-in ends.";
    const soon = () => raise("login-end", `Log-in ends at ${at}`, "After that every command but the E-STOP asks for a new log-in.", todo, "low");
    const ended = () => raise("login-end", `Log-in ended at ${at}`, "Throws, resets and moves ask for a new log-in now.", todo, "medium");
    // setTimeout holds at most 2^31-1 ms (24.8 days): a longer log-in is announced on a later page load
    loginTimers = [[end - LOGIN_NOTICE_MS, soon], [end, ended]]
      .filter(([when]) => when - Date.now() < 2 ** 31 - 1)
      .map(([when, fn]) => setTimeout(fn, Math.max(0, when - Date.now())));
  }

  function isStopKey(e) { return e.key === "Escape" || e.key === "Esc"; }

  function onKey(e) {
    if (!isStopKey(e) || e.repeat) return;
    if (!can("operator")) return;
    e.preventDefault();
    estop("Esc key");
  }

  /** Esc pressed inside the 3D view (viser's page, another origin): that page posts
   *  {slinger: "estop"} to us (server.console.scene injects the listener). */
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
  $("alarm-ack-all").addEventListener("click", acknowledgeAll);
  $("alarm-toggle").addEventListener("click", () => { alarmsOpen = !alarmsOpen; renderAlarms(); });
  // the stop acts on pointerdown (mouse, pen, touch), not on the click that follows the release:
  // no wait for the finger to lift or for the page to settle; a keyboard press still clicks
  let pointerAt = 0;
  $("estop").addEventListener("pointerdown", (e) => {
    if (e.button !== undefined && e.button > 0) return; // a right or middle button does not stop
    pointerAt = performance.now();
    estop(e.pointerType === "touch" ? "tap" : "button");
  });
  $("estop").addEventListener("click", () => { if (performance.now() - pointerAt > 1500) estop("button"); });
  $("estop-reset").addEventListener("click", resetEstop);
  $("machine").addEventListener("change", (e) => select(e.target.value));
  window.addEventListener("keydown", onKey, true); // capture: before any field or dialog sees it
  window.addEventListener("message", onFrameMessage);
  Live.on("machine", onMachine);
  Live.on("alarm", onAlarm);
  Live.on("connected", loadAlarms); // at the start and after a broken stream: what was missed
  for (const ev of ["connected", "resumed", "disconnected"]) Live.on(ev, render);
  document.addEventListener("DOMContentLoaded", init);

  return {
    machines, estop, raise, select, say, explainFailure, watchLogIn,
    get machineId() { return machineId; },
    onSelect: (fn) => selectHandlers.push(fn),
    setViserOrigin: (origin) => { viserOrigin = origin; },
    isEstopInFlight: () => !!estopInFlight,
  };
})();
