// Slinger operator console. Each page load opens its own console on the server (POST /api/consoles):
// its own machine, mode, target and 3D view (viser, bound by the websocket path /c/<id>), never
// shared with another operator. Machine state, throw progress, live samples and results arrive
// by live push (live.js); the page sends commands only (preview, throw). The machine selection,
// its state badge, E-STOP (button, Esc) and alarms live in the status strip (strip.js).
// A preview on screen is re-checked against the throw gate every PREVIEW_CHECK_MS (POST
// /api/previews/{id}/check): Throw is enabled only while it is valid, and when the machine is
// ready and the preview went stale or the machine moved, the page previews again by itself.
//
// One target, one truth: state.target is the console's target on the server, the one the 3D view
// marks. The x/y fields show it, except while the operator edits them (state.editing): then
// automatic previews wait and Preview and Throw are disabled until Set makes the typed point the
// target (or a click in the 3D view replaces it). A preview is drawn and used only while it is of
// state.target; it never writes the target or the fields. Throw names what it sends ("Throw 2D at
// 9.50 m") and sends state.target with the preview of it; the 3D confirm dialog names the target
// and the preview, and closes (nothing sent) when either changes while it is open.
// An automatic preview that fails (the twin's swing failed, or the request did: e.g. the gripper
// still swinging after a failed throw) is tried again by itself AUTO_RETRY_TRIES times,
// AUTO_RETRY_MS apart, while the machine is ready, the target the same, the fields not being edited
// and no throw in flight (state.retry); a preview the operator asked for is not (its target may be
// one the machine cannot reach: its message stays).
// A runtime that restarted (its RuntimeInfo epoch changed) leaves no stale target, preview or
// marker behind: the page clears them and says so.
// A log-in that ends takes the page to the log-in page (a command answered 401, or a reload after the
// LOGGED OUT banner); the aim typed in the fields comes back with the page, as typed and not yet Set
// (keepAim, restoreAim): the console on the server is a new one, and nothing is aimed at or thrown
// until the operator presses Set.
"use strict";

const state = { consoleId: null, viserPort: null, machines: Strip.machines, machineId: null, mode: "2d", target: null,
  targetReason: null, preview: null, previewKey: null, busy: false, throwId: null, throwStarted: null, shownState: null, sending: false, sends: 0, throwOver: null,
  check: null, checkAt: 0, checking: false, autoAt: 0, retry: null, typed: null, editing: false, confirming: null, epochs: new Map() };
const PREVIEW_CHECK_MS = 1000;
const AUTO_PREVIEW_MIN_MS = 4000; // at most one automatic preview per this interval
const AUTO_PREVIEW_BEFORE_STALE_S = 10; // preview again this long before the gate calls it stale
const AUTO_RETRY_TRIES = 3; // a failed automatic preview is tried again this many times
const AUTO_RETRY_MS = 3000; // this long after the failure
const JOINT_UNITS = { cabin_turn: ["cabin turn", "rad/s"], boom: ["boom", "rad/s"], dipper: ["dipper", "rad/s"],
  telescope: ["telescope", "m/s"] };
let plots = null;

const PHASE_PROGRESS = { requested: 0.05, preparing: 0.15, swinging: 0.45, released: 0.8, landed: 1, failed: 1, aborted: 1 };
const STATE_WORDS = { ready: "READY", not_ready: "NOT READY", throwing: "THROWING", estopped: "E-STOPPED", offline: "OFFLINE" };

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

const requestKey = () => JSON.stringify([state.machineId, state.mode, state.target]);
const selected = () => state.machines.get(state.machineId) || null;

// --- recovery advice for a state that is not ready -----------------------------------------------
function recoveryFor(m) {
  if (!Live.isConnected()) return "Check that the Slinger server is running; this page reconnects by itself.";
  if (m.state === "offline") return `Start the runtime of ${m.machine_id} (slinger runtime) or check its host and network.`;
  if (m.state === "estopped") return can("operator") ? "When the area is safe, press Reset E-STOP in the red banner." : "An operator must reset the E-STOP.";
  const r = (m.reason || "").toLowerCase();
  if (r.includes("policy")) return "Deploy a policy for this mode on the Policies page.";
  if (r.includes("real time")) return "Wait for the simulated machine to catch up; if it persists, restart its plant.";
  if (m.returning) return "The runtime drives the arm to its ready pose; E-STOP stops it.";
  if (m.recovery === "return_to_ready") {
    const last = m.return_result && !m.return_result.startsWith("reached") ? ` Last attempt: ${m.return_result}.` : "";
    return (can("operator") ? "Press Return to ready pose: the runtime drives the arm back slowly (E-STOP stops it)."
      : "An operator can return the machine to its ready pose.") + last;
  }
  if (r.includes("envelope") || r.includes("joint at end")) return "Move the machine back to its ready pose.";
  if (r.includes("machine offline")) return "Start the machine (slinger plant for the simulated machine) or check its link.";
  return "";
}

// --- machine state (the strip shows the badge, E-STOP banner and alarms) ---------------------------
function renderState() {
  const m = selected();
  const lost = !Live.isConnected();
  if (!m) {
    $("state-line").textContent = lost ? "Server unreachable." : "No machine known yet: start one with slinger up or slinger plant + slinger runtime.";
    updateButtons();
    return;
  }
  const words = lost ? "UNKNOWN (server unreachable)" : STATE_WORDS[m.state] || m.state;
  const phase = m.state === "throwing" && m.phase ? `: ${m.phase}` : "";
  $("state-line").textContent = `${m.machine_id}: ${words}${phase}` +
    (m.policies && m.policies[state.mode] ? ` · ${state.mode} policy ${m.policies[state.mode]}` : ` · no ${state.mode} policy`);
  $("state-reason").textContent = m.state === "ready" || lost ? "" : (m.reason ? `Why: ${m.reason}` : "");
  $("recovery").textContent = m.state === "ready" && !lost ? "" : recoveryFor(m);
  const offer = !lost && m.state === "not_ready" && m.recovery === "return_to_ready" && !m.returning;
  $("return-ready").hidden = !(offer && can("operator"));
  const progressing = m.state === "throwing";
  const returning = !lost && m.state === "not_ready" && m.returning;
  $("progress-box").hidden = !(progressing || returning);
  if (returning) {
    $("throw-progress").value = m.return_progress || 0;
    $("progress-text").textContent = `returning to the ready pose: ${Math.round(100 * (m.return_progress || 0))} %`;
  }
  if (progressing) {
    $("throw-progress").value = PHASE_PROGRESS[m.phase] || 0.1;
    const secs = state.throwStarted ? ` · ${((Date.now() - state.throwStarted) / 1000).toFixed(1)} s` : "";
    $("progress-text").textContent = `${m.phase || "running"}${secs}`;
  }
  updateButtons();
}

function onMachineEvent(m) {
  const seen = state.epochs.get(m.machine_id);
  if (m.epoch) state.epochs.set(m.machine_id, m.epoch);
  if (m.machine_id === state.machineId && seen && m.epoch && m.epoch !== seen) onRestart(m);
  if (m.machine_id !== state.machineId) return;
  const was = state.shownState;
  state.shownState = m.state;
  renderState();
  // ready again (a throw over, a payload reloaded): the gate judges the preview on screen now,
  // and the page previews again if it must, instead of at the next PREVIEW_CHECK_MS tick
  if (m.state === "ready" && was && was !== "ready") checkPreview();
}

/** The selected machine's runtime restarted (a new RuntimeInfo epoch): the target, preview and
 *  drawn throw are of the world before it; drop them here and in the 3D view, and say so. */
async function onRestart(m) {
  const at = new Date(m.epoch).toLocaleTimeString();
  state.editing = false;
  state.throwId = null; state.throwStarted = null;
  dropPreview(null);
  showLastResult("", "");
  if (state.consoleId) await putConsole({ clear: true }).catch(() => {});
  setStatus(`${m.machine_id} restarted (its runtime started at ${at}): the target, the preview and the drawn throw ` +
    "were of the machine before the restart and are cleared. Set a new target.", true);
}

// --- console state on the server ------------------------------------------------------------------
async function openConsole() {
  const c = await api("POST", "/api/consoles");
  state.consoleId = c.console_id;
  state.viserPort = c.viser_port;
  embedViser($("viser"), c);
  if (state.machineId) await putConsole({ machine_id: state.machineId, mode: state.mode });
}

/** The console's state from the server (a PUT's answer, or a click in its 3D view: ``click``).
 *  The fields follow the target unless the operator is editing them; a click ends the edit. A new
 *  target drops the preview of the old one (and a confirm dialog showing it). */
function applyConsole(c, click = false) {
  if (state.machineId && c.machine_id && c.machine_id !== state.machineId) return; // an answer to an older selection
  const before = JSON.stringify(state.target);
  state.target = c.target;
  state.targetReason = c.target_reason;
  if (click) state.editing = false;
  if (JSON.stringify(c.target) !== before) dropPreview("the target changed");
  if (c.target) {
    const d = Math.hypot(c.target[0], c.target[1]);
    const typed = state.typed;
    const moved = typed ? Math.hypot(typed[0] - c.target[0], typed[1] - c.target[1]) : 0;
    let text = `x ${fmt(c.target[0])}  y ${fmt(c.target[1])} m, ${fmt(d)} m from the turn axis`;
    if (typed && moved > 0.005) {
      // never move a typed target silently: say what was typed and where the target is now
      text += ` (snapped onto the 2D line: you typed x ${fmt(typed[0])} y ${fmt(typed[1])} m, the target is ${fmt(moved)} m from it)`;
    } else if (c.snapped) {
      text += " (snapped onto the 2D line)";
    }
    $("target").textContent = text;
  } else {
    $("target").textContent = "No target yet: click the ground inside the green band, or type x and y and press Set.";
  }
  if (!state.editing) { // the fields show the target the view marks and Throw sends
    $("target-x").value = c.target ? fmt(c.target[0]) : "";
    $("target-y").value = c.target ? fmt(c.target[1]) : "";
  }
  state.typed = null;
  $("target-reason").textContent = c.target_reason ? `Cannot throw here: ${c.target_reason}` : "";
  updateButtons();
}

async function putConsole(body) {
  const c = await api("PUT", `/api/consoles/${state.consoleId}`, body);
  applyConsole(c);
  return c;
}

async function selectMachine(id) {
  state.machineId = id;
  dropPreview("another machine was selected");
  $("throw-panel").hidden = true;
  if (state.consoleId) await putConsole({ machine_id: id, mode: state.mode }).catch((e) => setStatus(e.message, true));
  renderState();
  refreshHistory();
  if (aimToRestore) { const aim = aimToRestore; aimToRestore = null; await restoreAim(aim); }
}

/** True while the target of preview ``p`` is the console's target (to the millimetre). */
function previewOfTarget(p) {
  const t = state.target, pt = p && p.target_m;
  return !!(t && pt && Math.abs(t[0] - pt[0]) < 1e-3 && Math.abs(t[1] - pt[1]) < 1e-3);
}

function previewOnScreen() {
  return !!(state.preview && state.preview.status === "ok" && state.previewKey === requestKey() && previewOfTarget(state.preview));
}

/** Forget the preview on screen (``why``: said in the status line when one was shown), and
 *  close a confirm dialog that showed it. */
function dropPreview(why) {
  const had = !!state.preview;
  state.preview = null; state.previewKey = null; state.check = null; state.retry = null;
  $("preview-panel").hidden = true;
  if (state.confirming) closeConfirm(`${why}: nothing was sent`);
  if (had && why) setStatus(`Preview dropped: ${why}. Press Preview for the target on screen.`);
}

/** The Throw button's words: what it would send now (mode and distance of the target). */
function throwLabel() {
  if (!state.target) return "Throw";
  return `Throw ${state.mode.toUpperCase()} at ${fmt(Math.hypot(state.target[0], state.target[1]))} m`;
}

function updateButtons() {
  const m = selected();
  const ready = !!(m && m.state === "ready" && Live.isConnected() && state.target && !state.targetReason) && !state.busy &&
    !!(m.policies && m.policies[state.mode]) && // the runtime is ready for a mode with a policy: this one must have one
    !state.typed && !state.editing; // a typed target the server has not answered yet, or fields being edited
  $("preview").disabled = !ready;
  // Throw only with a preview of this request that the gate judged valid a moment ago
  const fresh = state.check && state.check.previewId === (state.preview && state.preview.id) &&
    Date.now() - state.checkAt < 3 * PREVIEW_CHECK_MS + 2000;
  const valid = previewOnScreen() && fresh && state.check.valid;
  const confirmed = state.mode !== "3d" || $("confirm-clearance").checked;
  $("throw").disabled = !(ready && valid && confirmed) || !!state.confirming || state.sending;
  $("throw").textContent = throwLabel();
  $("confirm-box").hidden = state.mode !== "3d";
  $("preview-panel").classList.toggle("stale", !!state.preview && !(previewOnScreen() && (!state.check || state.check.valid)));
  renderPreviewAge();
}

/** The operator's sentence for a failed gate condition (server.throws.gate). */
function gateWords(check) {
  switch (check.condition) {
    case "preview_stale": return "The preview is too old";
    case "machine_moved": return "The machine has moved since the preview";
    case "policy_changed": return "The machine's policy changed since the preview";
    case "preview_target": case "preview_other": return "The preview was made for another target";
    case "no_state": return "No state from the machine";
    default: return sentence(check.reason || "The preview is no longer valid").replace(/\.$/, "");
  }
}

function renderPreviewAge() {
  const el = $("preview-age");
  if (!previewOnScreen()) { el.textContent = ""; el.className = "preview-age"; return; }
  const age = state.check && state.check.age_s !== null && state.check.age_s !== undefined
    ? state.check.age_s + (Date.now() - state.checkAt) / 1000 : (Date.now() - state.previewAt) / 1000;
  const max = state.check && state.check.max_age_s;
  if (state.check && !state.check.valid && state.check.condition === "keep_out_scatter") {
    el.textContent = sentence(state.check.reason); // another preview would not help: another target does
    el.className = "preview-age error";
  } else if (state.check && !state.check.valid && state.check.condition === "machine_not_ready") {
    el.textContent = `${gateWords(state.check)}: waiting for it.`; // previews again by itself once it is ready
    el.className = "preview-age error";
  } else if (state.check && !state.check.valid) {
    el.textContent = `${gateWords(state.check)}: ${state.busy ? "previewing again…" : "preview again."}`;
    el.className = "preview-age error";
  } else {
    el.textContent = `preview ${Math.max(0, Math.round(age))} s old` + (max ? ` (valid ${Math.round(max)} s)` : "");
    el.className = "preview-age ok";
  }
}

/** Ask the server whether the preview on screen still passes the throw gate; refresh it by
 *  itself when the machine is ready and the preview went stale (or is about to) or it moved. */
async function checkPreview() {
  retryPreview();
  if (state.checking || !previewOnScreen() || !state.consoleId) { renderPreviewAge(); return; }
  const m = selected();
  // no judgement while a throw runs (until its result is in: state.throwOver): the swing outdates it
  if (!m || m.state === "throwing" || (state.throwId && state.throwOver !== state.throwId)) { renderPreviewAge(); return; }
  state.checking = true;
  const p = state.preview, sends = state.sends;
  try {
    const c = await api("POST", `/api/previews/${encodeURIComponent(p.id)}/check`,
      { machine_id: state.machineId, mode: state.mode, target: state.target });
    // a throw sent meanwhile used this preview: this judgement is of the machine before it
    if (state.preview !== p || state.sends !== sends) return;
    state.check = { ...c, previewId: p.id };
    state.checkAt = Date.now();
  } catch (e) {
    state.check = { valid: false, condition: "unknown", reason: e.message, previewId: p.id };
    state.checkAt = Date.now();
  } finally {
    state.checking = false;
  }
  updateButtons();
  const c = state.check;
  const ageing = c.valid && c.max_age_s && c.age_s > c.max_age_s - AUTO_PREVIEW_BEFORE_STALE_S;
  const restOk = m.state === "ready" && !state.busy && Date.now() - state.autoAt > AUTO_PREVIEW_MIN_MS;
  const refreshable = ["preview_stale", "machine_moved", "policy_changed", "preview_unknown"].includes(c.condition);
  if (restOk && !state.editing && (ageing || (!c.valid && refreshable)) && !$("preview").disabled) {
    state.autoAt = Date.now();
    doPreview(true);
  }
}

// --- preview ----------------------------------------------------------------------------------------
function showPreview(p) {
  $("preview-panel").hidden = false;
  $("pv-policy").textContent = `${p.policy_version} on ${p.machine_id}, ${p.mode}`;
  for (const id of ["out-down", "out-cross", "out-duration"]) $(id).textContent = "–";
  if (p.status !== "ok") {
    for (const id of ["pv-down", "pv-cross", "pv-duration", "pv-release", "pv-speeds", "pv-clearance", "pv-sigma"]) $(id).textContent = "–";
    setStatus(`Preview failed: the twin's swing ${p.reason}. Nothing was sent to the machine; pick another target.`, true);
    return;
  }
  $("pv-down").textContent = `${fmt(p.downrange_error_m)} m`;
  $("pv-cross").textContent = `${fmt(p.crossrange_error_m)} m`;
  $("pv-duration").textContent = `${fmt(p.duration_s)} s (release at ${fmt(p.release_after_s)} s)`;
  const v = p.release_vel_mps;
  $("pv-release").textContent = `${fmt(Math.hypot(v[0], v[1], v[2]))} m/s`;
  $("pv-speeds").textContent = Object.entries(p.peak_joint_speeds)
    .map(([k, x]) => { const [name, unit] = JOINT_UNITS[k] || [k.replace(/_/g, " "), ""]; return `${name} ${fmt(x)} ${unit}`.trim(); }).join(", ");
  const c = p.clearance;
  $("pv-clearance").textContent = c.inside ? `inside (reach ${fmt(c.max_radius_m, 1)} m of ${fmt(c.radius_m, 1)} m)` : `OUTSIDE: ${c.reasons.join(", ")}`;
  $("pv-clearance").className = c.inside ? "ok" : "error";
  $("pv-sigma").textContent = p.mc && p.mc.ellipse
    ? `${fmt(p.mc.sigma_downrange_m, 3)} / ${fmt(p.mc.sigma_crossrange_m, 3)} m (${p.mc.rollouts} rollouts)` : "computing…";
}

/** True while a throw is on its way or running (until its result is read: state.throwOver). */
const throwInFlight = () => state.sending || !!(state.throwId && state.throwOver !== state.throwId);

/** Run the automatic preview again that state.retry waits for, once its time has come and the
 *  console may preview by itself: the machine ready, the same machine, mode and target, the fields
 *  not being edited, no throw in flight and no preview running (until then it waits). Another
 *  request (target, mode or machine) ends the wait. */
function retryPreview() {
  const r = state.retry;
  if (!r || r.at === null || Date.now() < r.at) return;
  if (requestKey() !== r.key) { state.retry = null; return; }
  const m = selected();
  if (!m || m.state !== "ready" || state.editing || state.busy || throwInFlight() || $("preview").disabled) return;
  r.at = null; // on its way: doPreview schedules the next try or ends the wait
  state.autoAt = Date.now();
  doPreview(true);
}

/** An automatic preview of request ``key`` failed (``why``: the twin's reason, or the request's
 *  error with ``requestError``); ``tries``: the automatic tries of it so far. Preview again in
 *  AUTO_RETRY_MS (retryPreview), or after AUTO_RETRY_TRIES tries leave it to the operator. */
function scheduleRetry(key, why, requestError, tries) {
  if (tries >= AUTO_RETRY_TRIES) {
    state.retry = null;
    setStatus(`The automatic preview failed ${tries + 1} times in a row (${why}). Nothing was sent to the machine; ` +
      "press Preview once the machine has settled, or pick another target.", true);
    return;
  }
  state.retry = { key, tries: tries + 1, at: Date.now() + AUTO_RETRY_MS };
  const wait = `previewing again in ${Math.round(AUTO_RETRY_MS / 1000)} s (automatic try ${tries + 1} of ${AUTO_RETRY_TRIES})`;
  setStatus(requestError ? `The automatic preview failed (${why}): ${wait}.`
    : `The machine is still settling: the twin's preview failed (${why}). Nothing was sent to the machine; ${wait}.`);
  setTimeout(retryPreview, AUTO_RETRY_MS + 50);
}

/** Preview the console's target: the nominal rollout first (shown alone at once), then the
 *  Monte Carlo ellipse. A preview whose target is no longer the console's is dropped, never drawn.
 *  ``auto``: the page previews by itself (checkPreview, retryPreview); such a preview that fails
 *  is tried again (scheduleRetry), one the operator asked for is not. */
async function doPreview(auto = false) {
  if (!state.target) return;
  const retry = auto && state.retry && state.retry.key === requestKey() ? state.retry : null;
  state.retry = null; // an operator's preview ends the wait for an automatic one
  state.busy = true; updateButtons();
  const body = { machine_id: state.machineId, mode: state.mode, target: state.target };
  const key = requestKey();
  const current = () => state.previewKey === key && requestKey() === key && !state.editing;
  setStatus(retry ? `Previewing again in the twin (automatic try ${retry.tries} of ${AUTO_RETRY_TRIES})…`
    : auto ? "The machine or the preview changed: previewing again in the twin…" : "Previewing in the twin…");
  let failed = null, requestError = false; // why this preview failed, if it did
  try {
    const quick = await api("POST", "/api/previews", { ...body, rollouts: 1 });
    if (requestKey() !== key) return; // the target, mode or machine changed meanwhile: this preview is of another throw
    setPreview(quick, key);
    if (quick.status !== "ok") failed = quick.reason || "no reason given";
    if (quick.status === "ok") {
      setStatus("Nominal preview shown; computing the 1σ scatter ellipse…");
      let full = null;
      // the ellipse of the nominal just shown: from its machine state, its rollout reused (extends)
      try { full = await api("POST", "/api/previews", { ...body, extends: quick.id }); } catch (e) {
        $("pv-sigma").textContent = `unavailable (${e.message})`;
        if (current()) setStatus(`Preview of the nominal rollout only (the 1σ ellipse failed: ${e.message}).`);
      }
      if (full && current()) {
        setPreview(full, key);
        if (full.status !== "ok") failed = full.reason || "no reason given";
        else setStatus(`Preview of x ${fmt(full.target_m[0])} y ${fmt(full.target_m[1])} m: ${fmt(full.downrange_error_m)} m downrange, ` +
          `${fmt(full.crossrange_error_m)} m crossrange. Throw enables once the server judges it valid.`);
      }
    }
  } catch (e) {
    if (requestKey() === key) {
      dropPreview(null);
      setStatus(`No preview: ${e.message}`, true);
      failed = e.message; requestError = true;
    }
  } finally {
    state.busy = false; updateButtons();
  }
  if (auto && failed !== null && requestKey() === key) scheduleRetry(key, failed, requestError, retry ? retry.tries : 0);
  checkPreview(); // at once, not at the next tick: Throw enables when the gate says so
}

/** Make ``p`` (a preview of request ``key``) the preview on screen and draw it in the 3D view.
 *  Throw waits for the server's gate to judge it against the machine as it is now (checkPreview):
 *  a machine still settling after a throw, or scatter into a keep-out zone, must not leave Throw
 *  enabled on the preview's own word. */
function setPreview(p, key) {
  if (state.confirming && (!state.preview || state.preview.id !== p.id)) closeConfirm("the preview changed: nothing was sent");
  state.preview = p; state.previewKey = key; state.previewAt = Date.now();
  state.check = null;
  showPreview(p);
  // the answer (the console) is not applied: a preview never changes the target or the fields
  api("POST", `/api/consoles/${state.consoleId}/preview`, { preview_id: p.id }).catch(() => {});
  updateButtons();
}

// --- throw ------------------------------------------------------------------------------------------
/** Send the throw the page shows: the console's target with the preview of it. In 3D a dialog
 *  confirms exactly that target and preview; it closes, and nothing is sent, if either changes. */
async function doThrow() {
  if (!previewOnScreen()) { setStatus("No valid preview of this target: press Preview first.", true); return; }
  const p = state.preview, key = requestKey(), target = state.target.slice();
  const where = `x ${fmt(target[0])} y ${fmt(target[1])} m (${fmt(Math.hypot(target[0], target[1]))} m)`;
  if (state.mode === "3d") {
    state.confirming = { previewId: p.id };
    updateButtons();
    const ok = await confirmAction(`Throw 3D at ${fmt(Math.hypot(target[0], target[1]))} m?`,
      `${state.machineId} will turn its cabin and throw at ${where}, as previewed (preview ${p.id.slice(0, 8)}: ` +
      `${fmt(p.downrange_error_m)} m downrange, ${fmt(p.crossrange_error_m)} m crossrange). ` +
      "Only confirm if the swept clearance zone (yellow) is clear of people and objects.", "Throw in 3D");
    state.confirming = null;
    updateButtons();
    if (!ok) { if (!state.confirmClosedWhy) setStatus("3D throw cancelled."); state.confirmClosedWhy = null; return; }
    if (state.preview !== p || requestKey() !== key || !previewOnScreen()) {
      setStatus("The preview or the target changed while the dialog was open: nothing was sent. Press Throw again for the new one.", true);
      return;
    }
  }
  $("throw").disabled = true;
  state.sending = true; state.sends += 1; // no Throw (and no judgement of this preview) until the answer
  setStatus(`Sending the throw at ${where}…`);
  try {
    const body = { machine_id: state.machineId, mode: state.mode, target, preview_id: p.id };
    if (state.mode === "3d") body.confirm_clearance = $("confirm-clearance").checked;
    const r = await api("POST", "/api/throws", body);
    state.throwId = r.id; state.throwStarted = Date.now();
    // the gate's last judgement was of the machine before this throw: void until it judges again
    // (checkPreview, once the throw is over), so Throw never re-enables on a judgement the swing outdated
    state.check = { valid: false, condition: "preview_used", reason: "the preview was used for this throw", previewId: p.id };
    state.checkAt = Date.now();
    $("confirm-clearance").checked = false;
    setStatus(`Throw ${r.id.slice(0, 8)} at ${where} accepted (policy ${r.policy_version || "?"}): running…`);
    showLastResult(`Throw ${r.id.slice(0, 8)} running…`, "");
    startThrowPanel(r.id);
  } catch (e) {
    setStatus(`The throw was not sent. ${e.message}`, true);
  } finally {
    state.sending = false;
    updateButtons();
  }
}

/** Close the open confirm dialog as cancelled, saying ``why`` in the status line. */
function closeConfirm(why) {
  state.confirmClosedWhy = why;
  cancelConfirm();
  // in the strip (it stays 20 s): the status line below goes on with the preview that replaced it
  Strip.say(`The confirm dialog closed: ${why}. Check the preview and press Throw again.`);
}

function startThrowPanel(throwId) {
  $("throw-panel").hidden = false;
  $("tp-id").textContent = `${throwId.slice(0, 8)} · live`;
  $("tp-result").textContent = "In progress…";
  $("tp-result").className = "result";
  $("scrub").disabled = true;
  plots.reset();
}

/** The last throw's result next to Preview/Throw and over the 3D view. */
function showLastResult(text, kind) {
  for (const id of ["result", "view-result"]) {
    $(id).textContent = text;
    $(id).className = `${id === "result" ? "result last-result" : "view-result"} ${kind}`;
    $(id).hidden = !text;
  }
}

/** One line for a stored throw: landed with its error in metres, or what failed and what to do. */
function resultWords(t) {
  if (t.status === "landed") {
    const err = Math.hypot(t.downrange_error_m || 0, t.crossrange_error_m || 0);
    return `Throw ${t.id.slice(0, 8)} LANDED ${fmt(err)} m from the target ` +
      `(${fmt(t.downrange_error_m)} m downrange, ${fmt(t.crossrange_error_m)} m crossrange).`;
  }
  const m = selected();
  const why = Strip.explainFailure({ ...t, simulated: m && m.simulated });
  return `Throw ${t.id.slice(0, 8)} ${t.status.toUpperCase()}: ${why.text} ${why.todo}`;
}

async function showResult(throwId) {
  let t, tr = null;
  try { t = await api("GET", `/api/throws/${throwId}`); } catch (e) { return; }
  if (t.machine_id !== state.machineId) return;
  $("throw-panel").hidden = false;
  $("tp-id").textContent = throwId.slice(0, 8);
  const ok = t.status === "landed";
  $("tp-result").textContent = ok
    ? `Landed at ${fmtVec(t.impact)} m: ${fmt(t.downrange_error_m)} m downrange, ${fmt(t.crossrange_error_m)} m crossrange of the target.`
    : `${t.status.toUpperCase()}: ${t.failure_reason || "no reason given"}`;
  $("tp-result").className = `result ${ok ? "ok" : "error"}`;
  showLastResult(resultWords(t), ok ? "ok" : "error");
  // the thrown preview beside the outcome (the preview panel above moves on to the next preview)
  const pv = t.preview;
  $("tp-compare").textContent = pv && pv.downrange_error_m !== undefined && pv.downrange_error_m !== null
    ? `Preview (twin): ${fmt(pv.downrange_error_m)} m downrange, ${fmt(pv.crossrange_error_m)} m crossrange · outcome: ` +
      (ok ? `${fmt(t.downrange_error_m)} m downrange, ${fmt(t.crossrange_error_m)} m crossrange` : t.status)
    : "";
  setStatus(ok ? "Throw done: the machine returns to rest, then the preview refreshes by itself." :
    "The throw failed: see the alarm at the top.", !ok);
  if (t.preview && state.preview && state.preview.id === t.preview.id) {
    $("out-down").textContent = `${fmt(t.downrange_error_m)} m`;
    $("out-cross").textContent = `${fmt(t.crossrange_error_m)} m`;
    $("out-duration").textContent = t.duration_s !== undefined && t.duration_s !== null ? `${fmt(t.duration_s)} s` : "–";
  }
  // the throw is over once its result is read: the next judgement (and preview) need not wait
  // for its trajectory to load (checkPreview)
  if (throwId === state.throwId) state.throwOver = throwId;
  try { tr = await api("GET", `/api/throws/${throwId}/trajectory`); } catch (e) { /* no telemetry */ }
  if (tr) { plots.showTrajectory(tr); plots.enableScrubber(); }
  if (throwId === state.throwId) { state.throwId = null; state.throwStarted = null; }
}

const FINAL_STATUSES = ["landed", "failed", "aborted", "lost"]; // server.db.models.FINAL_STATUSES (tests/test_web_pages.py holds them equal)

/** The live stream broke while throw ``throwId`` ran: its result event may have been missed.
 *  Show its result if it is over (else its result event is still to come). */
async function catchUpThrow(throwId) {
  let t;
  try { t = await api("GET", `/api/throws/${encodeURIComponent(throwId)}`); } catch (e) { return; }
  if (throwId === state.throwId && FINAL_STATUSES.includes(t.status)) showResult(throwId);
}

async function doReturnToReady() {
  const mid = state.machineId;
  const ok = await confirmAction("Return to the ready pose?", `${mid} will move boom, dipper and telescope slowly to ` +
    "its ready pose (the cabin keeps its angle). Only confirm if the area around the arm is clear; E-STOP stops it.",
  "Return to ready pose");
  if (!ok) return;
  $("return-ready").disabled = true;
  try {
    await api("POST", `/api/machines/${encodeURIComponent(mid)}/return-to-ready`);
    setStatus(`${mid} is returning to its ready pose…`);
  } catch (e) {
    setStatus(`Return to the ready pose refused. ${e.message}`, true);
  } finally {
    $("return-ready").disabled = false;
  }
}

// --- history ----------------------------------------------------------------------------------------
const newestHistory = latestOnly(); // a result or another machine asks again: only the newest answer draws

async function refreshHistory() {
  if (!state.machineId) return;
  const mine = newestHistory();
  let rows;
  try { rows = await api("GET", `/api/throws?machine_id=${encodeURIComponent(state.machineId)}&limit=10`); } catch (e) { return; }
  if (!mine()) return; // of an older selection or an older result
  const body = $("history").querySelector("tbody");
  body.innerHTML = "";
  $("history-empty").hidden = rows.length > 0;
  $("history").hidden = rows.length === 0;
  for (const t of rows) {
    const tr = body.insertRow();
    tr.dataset.throwId = t.id;
    const err = t.downrange_error_m === null ? "–" : `${fmt(t.downrange_error_m)} / ${fmt(t.crossrange_error_m)}`;
    const cells = [new Date(t.requested_at).toLocaleTimeString(), t.mode, fmt(Math.hypot(t.target[0], t.target[1]), 1), err,
      t.status + (t.failure_reason ? `: ${t.failure_reason}` : "")];
    cells.forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i === 4) td.className = `status-${t.status}`; });
    const a = document.createElement("a");
    a.href = `history.html?throw=${t.id}`; a.textContent = "details";
    tr.cells[0].append(" ", a);
  }
}

// --- a stored throw from the History page, drawn in this page's 3D view -------------------------------
async function showReplay(throwId) {
  let t;
  try { t = await api("GET", `/api/throws/${encodeURIComponent(throwId)}`); } catch (e) { setStatus(`No such throw to show. ${e.message}`, true); return; }
  Strip.select(t.machine_id);
  if (state.machineId !== t.machine_id) await selectMachine(t.machine_id);
  await showResult(throwId);
  const draw = () => api("POST", `/api/throws/${encodeURIComponent(throwId)}/replay`).catch(() => {});
  // the 3D view connects after the page: draw once it is there, and once more for a slow connection
  $("viser").addEventListener("load", () => setTimeout(draw, 1500), { once: true });
  setTimeout(draw, 6000);
  setStatus(`Showing throw ${throwId.slice(0, 8)} of ${t.machine_id} from the History page: its path and impact in the 3D view, its plots below.`);
}

// --- the aim across a log-in ------------------------------------------------------------------------
const AIM_KEY = "slinger.console.aim"; // this tab's sessionStorage: the fields, mode and machine
const AIM_KEEP_MS = 24 * 3600 * 1000; // an aim kept longer ago than this is dropped

/** The console's mode is now ``mode`` ("2d" or "3d"; the radio buttons already show it): the preview
 *  of the other mode goes, and the server's console follows. */
async function setMode(mode) {
  state.mode = mode;
  dropPreview(`the mode is now ${state.mode.toUpperCase()}`);
  await putConsole({ mode: state.mode }).catch((err) => setStatus(err.message, true));
  renderState();
}

/** Keep the x/y fields (as typed), the mode and the machine for this page's return from the log-in
 *  page; nothing when the fields are empty. */
function keepAim() {
  const x = $("target-x").value.trim(), y = $("target-y").value.trim();
  if (!x || !y) return;
  try {
    sessionStorage.setItem(AIM_KEY, JSON.stringify({ x, y, mode: state.mode, machine: state.machineId, at: Date.now() }));
  } catch (e) { /* storage refused: the aim is lost, as before */ }
}

/** The aim keepAim kept (then dropped from storage), or null: none, unreadable or too old. */
function takeKeptAim() {
  let aim = null;
  try { aim = JSON.parse(sessionStorage.getItem(AIM_KEY) || "null"); sessionStorage.removeItem(AIM_KEY); } catch (e) { return null; }
  if (!aim || typeof aim.x !== "string" || typeof aim.y !== "string" || !(Date.now() - aim.at < AIM_KEEP_MS)) return null;
  return aim;
}
let aimToRestore = null; // takeKeptAim's at the page's load, put back at the first machine selection

/** ``aim`` (takeKeptAim's) back in the fields as an edit not yet Set. Only for the machine it was
 *  aimed on: with another one selected, the page says so and leaves the fields. */
async function restoreAim(aim) {
  if (aim.machine && aim.machine !== state.machineId) {
    setStatus(`Your aim from before the log-in (x ${aim.x} y ${aim.y} m) was on ${aim.machine}; ${state.machineId || "no machine"} is selected now, so it is not put back.`);
    return;
  }
  if ((aim.mode === "2d" || aim.mode === "3d") && aim.mode !== state.mode) {
    for (const r of document.querySelectorAll("input[name=mode]")) r.checked = r.value === aim.mode;
    await setMode(aim.mode);
  }
  $("target-x").value = aim.x;
  $("target-y").value = aim.y;
  state.editing = true;
  setStatus(`Your aim from before the log-in is back in the fields: x ${aim.x} y ${aim.y} m, ${state.mode.toUpperCase()}. ` +
    "Press Set (or Enter) to aim there; Preview and Throw wait until then.");
  updateButtons();
}

// --- wiring -----------------------------------------------------------------------------------------
async function setTypedTarget(e) {
  e.preventDefault();
  const x = parseFloat($("target-x").value), y = parseFloat($("target-y").value);
  if (!Number.isFinite(x) || !Number.isFinite(y)) { setStatus("Type x and y in metres.", true); return; }
  state.typed = [x, y];
  state.editing = false; // the answer writes the target (snapped in 2D) into the fields
  updateButtons(); // no Preview of the old target while the typed one is on its way
  try { await putConsole({ target: [x, y, 0] }); } catch (err) { state.typed = null; state.editing = true; setStatus(err.message, true); updateButtons(); }
}

/** A field edited by hand: the target is what Set will make it, not what the fields show yet. */
function onFieldEdit() {
  if (state.editing) return;
  state.editing = true;
  setStatus("Editing the target: press Set (or Enter) to aim there. Preview and Throw wait until then.");
  updateButtons();
}

function wireLive() {
  Live.on("machine", onMachineEvent);
  Live.on("console", (c) => applyConsole(c, true)); // a click in this console's 3D view
  Live.on("throw", (ev) => {
    if (ev.machine_id !== state.machineId) return;
    if (ev.throw_id !== state.throwId && ["preparing", "swinging"].includes(ev.phase)) {
      state.throwId = ev.throw_id; state.throwStarted = Date.now() - 1000 * ev.elapsed_s;
      startThrowPanel(ev.throw_id);
    }
    const m = selected();
    if (m) { m.phase = ev.phase; renderState(); }
  });
  Live.on("job", (j) => { // a preview of this operator's that waits on the worker says why it takes longer
    if (j && j.kind === "preview" && j.status === "running" && j.message && state.busy && session.user
      && j.requested_by === session.user.username) setStatus(`Previewing in the twin: ${j.message}…`);
  });
  Live.on("sample", (s) => { if (s.machine_id === state.machineId && s.throw_id === state.throwId) plots.addSample(s); });
  Live.on("result", (r) => { showResult(r.throw_id); refreshHistory(); });
  Live.on("disconnected", renderState);
  Live.on("resumed", renderState);
  Live.on("connected", async () => {
    try { await api("GET", `/api/consoles/${state.consoleId}`); } catch (e) { await openConsole().catch(() => {}); }
    renderState(); refreshHistory();
    if (state.throwId) catchUpThrow(state.throwId);
  });
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  plots = new ThrowPlots($("plots"));
  plots.attachScrubber($("scrub"), $("scrub-play"), $("scrub-readout"));
  $("throw").addEventListener("click", doThrow);
  $("preview").addEventListener("click", () => doPreview(false));
  $("return-ready").addEventListener("click", doReturnToReady);
  $("target-form").addEventListener("submit", setTypedTarget);
  for (const id of ["target-x", "target-y"]) $(id).addEventListener("input", onFieldEdit);
  $("confirm-clearance").addEventListener("change", updateButtons);
  for (const r of document.querySelectorAll("input[name=mode]")) r.addEventListener("change", (e) => setMode(e.target.value));
  try { await openConsole(); } catch (e) { setStatus(`3D view unavailable. ${e.message}`, true); }
  aimToRestore = takeKeptAim();
  onLeaveForLogIn(keepAim);
  window.addEventListener("pagehide", () => { if (Live.isLoggedOut()) keepAim(); }); // a reload after LOGGED OUT
  Strip.onSelect((id) => selectMachine(id));
  if (Strip.machineId) await selectMachine(Strip.machineId);
  setInterval(checkPreview, PREVIEW_CHECK_MS);
  const replay = new URLSearchParams(location.search).get("replay");
  if (replay) showReplay(replay);
  wireLive();
  Live.start(state.consoleId);
}

document.addEventListener("DOMContentLoaded", init);
