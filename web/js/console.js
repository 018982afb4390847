// Slinger operator console. Each page load opens its own console on the server (POST /api/consoles):
// its own machine, mode, target and 3D view (viser, bound by the websocket path /c/<id>), never
// shared with another operator. Machine state, throw progress, live samples and results arrive
// by live push (live.js); the page sends commands only (preview, throw, E-STOP, reset).
"use strict";

const state = { consoleId: null, viserPort: null, machines: new Map(), machineId: null, mode: "2d", target: null,
  targetReason: null, preview: null, previewKey: null, busy: false, throwId: null, throwStarted: null };
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

// --- machine state, shown in the header badge, the state card and the E-STOP banner ---------------
function renderState() {
  const m = selected();
  const badge = $("machine-state");
  const lost = !Live.isConnected();
  if (!m) {
    badge.textContent = lost ? "UNKNOWN: server unreachable" : "no machine";
    badge.className = "state-badge state-unknown";
    $("state-line").textContent = lost ? "Server unreachable." : "No machine known yet: start one with slinger up or slinger plant + slinger runtime.";
    updateButtons();
    return;
  }
  const st = lost ? "unknown" : m.state;
  const words = lost ? "UNKNOWN (server unreachable)" : STATE_WORDS[m.state] || m.state;
  const phase = m.state === "throwing" && m.phase ? `: ${m.phase}` : "";
  badge.textContent = `${m.machine_id} ${words}${phase}`;
  badge.className = `state-badge state-${st}`;
  $("machine-kind").hidden = !m.simulated;
  $("state-line").textContent = `${m.machine_id}: ${words}${phase}` +
    (m.policies && m.policies[state.mode] ? ` · ${state.mode} policy ${m.policies[state.mode]}` : ` · no ${state.mode} policy`);
  $("state-reason").textContent = m.state === "ready" || lost ? "" : (m.reason ? `Why: ${m.reason}` : "");
  $("recovery").textContent = m.state === "ready" && !lost ? "" : recoveryFor(m);
  const banner = $("estop-banner");
  banner.hidden = m.state !== "estopped";
  $("estop-machine").textContent = m.machine_id;
  $("estop-text").textContent = m.estop_reason ? `Reason: ${m.estop_reason}. Throws are refused until Reset.` : "Throws are refused until Reset.";
  document.body.classList.toggle("estopped", m.state === "estopped");
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

function renderMachineList() {
  const sel = $("machine");
  const ids = [...state.machines.keys()].sort();
  if (sel.options.length !== ids.length || [...sel.options].some((o, i) => o.value !== ids[i])) {
    sel.innerHTML = "";
    for (const id of ids) sel.add(new Option(id, id));
    sel.value = state.machineId || "";
  }
  for (const o of sel.options) {
    const m = state.machines.get(o.value);
    o.textContent = `${o.value} (${(STATE_WORDS[m.state] || m.state).toLowerCase()})`;
  }
}

function onMachineEvent(m) {
  const known = state.machines.has(m.machine_id);
  state.machines.set(m.machine_id, m);
  if (!known) renderMachineList();
  if (!state.machineId) selectMachine(m.machine_id);
  renderMachineList();
  if (m.machine_id === state.machineId) renderState();
}

// --- console state on the server ------------------------------------------------------------------
async function openConsole() {
  const c = await api("POST", "/api/consoles");
  state.consoleId = c.console_id;
  state.viserPort = c.viser_port;
  const ws = `${location.protocol === "https:" ? "wss" : "ws"}://${location.hostname}:${c.viser_port}${c.viser_path}`;
  $("viser").src = `${location.protocol}//${location.hostname}:${c.viser_port}/?websocket=${encodeURIComponent(ws)}`;
  if (state.machineId) await putConsole({ machine_id: state.machineId, mode: state.mode });
}

function applyConsole(c) {
  if (state.machineId && c.machine_id && c.machine_id !== state.machineId) return; // an answer to an older selection
  state.target = c.target;
  state.targetReason = c.target_reason;
  if (c.target) {
    const d = Math.hypot(c.target[0], c.target[1]);
    $("target").textContent = `x ${fmt(c.target[0])}  y ${fmt(c.target[1])} m, ${fmt(d, 1)} m from the turn axis` +
      (c.snapped ? " (snapped onto the 2D line)" : "");
  } else {
    $("target").textContent = "No target yet: click the ground inside the green band.";
  }
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
  $("machine").value = id;
  state.preview = null;
  $("preview-panel").hidden = true;
  $("throw-panel").hidden = true;
  if (state.consoleId) await putConsole({ machine_id: id, mode: state.mode }).catch((e) => setStatus(e.message, true));
  renderState();
  refreshHistory();
}

function updateButtons() {
  const m = selected();
  const ready = !!(m && m.state === "ready" && Live.isConnected() && state.target && !state.targetReason) && !state.busy;
  $("preview").disabled = !ready;
  const previewed = state.preview && state.preview.status === "ok" && state.previewKey === requestKey();
  const confirmed = state.mode !== "3d" || $("confirm-clearance").checked;
  $("throw").disabled = !(ready && previewed && confirmed);
  $("confirm-box").hidden = state.mode !== "3d";
  $("preview-panel").classList.toggle("stale", !!state.preview && state.previewKey !== requestKey());
}

// --- preview ----------------------------------------------------------------------------------------
function showPreview(p) {
  $("preview-panel").hidden = false;
  $("pv-policy").textContent = `${p.policy_version} on ${p.machine_id}, ${p.mode}`;
  for (const id of ["out-down", "out-cross", "out-duration"]) $(id).textContent = "–";
  if (p.status !== "ok") {
    for (const id of ["pv-down", "pv-cross", "pv-duration", "pv-release", "pv-speeds", "pv-clearance", "pv-sigma"]) $(id).textContent = "–";
    setStatus(`Preview failed: the twin's swing ${p.reason}. Nothing was sent to the machine.`, true);
    return;
  }
  $("pv-down").textContent = `${fmt(p.downrange_error_m)} m`;
  $("pv-cross").textContent = `${fmt(p.crossrange_error_m)} m`;
  $("pv-duration").textContent = `${fmt(p.duration_s)} s (release at ${fmt(p.release_after_s)} s)`;
  const v = p.release_vel_mps;
  $("pv-release").textContent = `${fmt(Math.hypot(v[0], v[1], v[2]))} m/s`;
  $("pv-speeds").textContent = Object.entries(p.peak_joint_speeds).map(([k, x]) => `${k} ${fmt(x)}`).join(", ");
  const c = p.clearance;
  $("pv-clearance").textContent = c.inside ? `inside (reach ${fmt(c.max_radius_m, 1)} m of ${fmt(c.radius_m, 1)} m)` : `OUTSIDE: ${c.reasons.join(", ")}`;
  $("pv-clearance").className = c.inside ? "ok" : "error";
  $("pv-sigma").textContent = p.mc && p.mc.ellipse
    ? `${fmt(p.mc.sigma_downrange_m, 3)} / ${fmt(p.mc.sigma_crossrange_m, 3)} m (${p.mc.rollouts} rollouts)` : "computing…";
}

async function doPreview() {
  state.busy = true; updateButtons();
  const body = { machine_id: state.machineId, mode: state.mode, target: state.target };
  const key = requestKey();
  setStatus("Previewing in the twin…");
  try {
    const quick = await api("POST", "/api/previews", { ...body, rollouts: 1 });
    state.preview = quick; state.previewKey = key;
    showPreview(quick);
    await api("POST", `/api/consoles/${state.consoleId}/preview`, { preview_id: quick.id }).then(applyConsole).catch(() => {});
    if (quick.status === "ok") {
      let full = null;
      try { full = await api("POST", "/api/previews", body); } catch (e) {
        $("pv-sigma").textContent = `unavailable (${e.message})`;
        setStatus(`Preview ready (nominal rollout only; the 1σ ellipse failed: ${e.message}). Press Throw to send it.`);
      }
      if (full) {
        state.preview = full;
        showPreview(full);
        await api("POST", `/api/consoles/${state.consoleId}/preview`, { preview_id: full.id }).then(applyConsole).catch(() => {});
        setStatus(`Preview ready: ${fmt(full.downrange_error_m)} m downrange, ${fmt(full.crossrange_error_m)} m crossrange. Press Throw to send it.`);
      }
    }
  } catch (e) {
    state.preview = null;
    $("preview-panel").hidden = true;
    setStatus(`Refused: ${e.message}`, true);
  } finally {
    state.busy = false; updateButtons();
  }
}

// --- throw ------------------------------------------------------------------------------------------
async function doThrow() {
  if (state.mode === "3d") {
    const d = Math.hypot(state.target[0], state.target[1]);
    const ok = await confirmAction("Throw in 3D?", `${state.machineId} will turn its cabin and throw at ${fmt(d, 1)} m. ` +
      "Only confirm if the swept clearance zone (yellow) is clear of people and objects.", "Throw in 3D");
    if (!ok) { setStatus("3D throw cancelled."); return; }
  }
  $("throw").disabled = true;
  setStatus("Sending throw…");
  try {
    const body = { machine_id: state.machineId, mode: state.mode, target: state.target, preview_id: state.preview.id };
    if (state.mode === "3d") body.confirm_clearance = $("confirm-clearance").checked;
    const r = await api("POST", "/api/throws", body);
    state.throwId = r.id; state.throwStarted = Date.now();
    $("confirm-clearance").checked = false;
    setStatus(`Throw ${r.id.slice(0, 8)} accepted (policy ${r.policy_version || "?"}): watch it live below.`);
    startThrowPanel(r.id);
  } catch (e) {
    setStatus(`Refused: ${e.message}`, true);
  } finally {
    updateButtons();
  }
}

function startThrowPanel(throwId) {
  $("throw-panel").hidden = false;
  $("tp-id").textContent = `${throwId.slice(0, 8)} · live`;
  $("tp-result").textContent = "In progress…";
  $("tp-result").className = "result";
  $("scrub").disabled = true;
  plots.reset();
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
  if (t.preview && state.preview && state.preview.id === t.preview.id) {
    $("out-down").textContent = `${fmt(t.downrange_error_m)} m`;
    $("out-cross").textContent = `${fmt(t.crossrange_error_m)} m`;
    $("out-duration").textContent = t.duration_s !== undefined && t.duration_s !== null ? `${fmt(t.duration_s)} s` : "–";
  }
  try { tr = await api("GET", `/api/throws/${throwId}/trajectory`); } catch (e) { /* no telemetry */ }
  if (tr) { plots.showTrajectory(tr); plots.enableScrubber(); }
  if (throwId === state.throwId) { state.throwId = null; state.throwStarted = null; }
}

// --- E-STOP -----------------------------------------------------------------------------------------
async function doEstop() {
  const mid = state.machineId;
  if (!mid) { setStatus("E-STOP: no machine selected", true); return; }
  setStatus(`E-STOP sent to ${mid}…`, true);
  try {
    const r = await api("POST", `/api/machines/${encodeURIComponent(mid)}/estop`, { reason: "E-STOP in the console" });
    setStatus(`E-STOP confirmed by the runtime of ${r.machine_id}: valves neutral` +
      (r.aborted_throw_id ? `, throw ${r.aborted_throw_id.slice(0, 8)} aborted` : "") + ".", true);
  } catch (e) {
    setStatus(`E-STOP NOT CONFIRMED for ${mid}: ${e.message}. Use the machine's own emergency stop.`, true);
  }
}

async function doEstopReset() {
  const mid = state.machineId;
  try {
    await api("POST", `/api/machines/${encodeURIComponent(mid)}/estop/reset`);
    setStatus(`E-STOP of ${mid} reset: waiting for the runtime to confirm…`);
  } catch (e) {
    setStatus(`Reset refused: ${e.message}`, true);
  }
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
    setStatus(`Return to the ready pose refused: ${e.message}`, true);
  } finally {
    $("return-ready").disabled = false;
  }
}

// --- history ----------------------------------------------------------------------------------------
async function refreshHistory() {
  if (!state.machineId) return;
  let rows;
  try { rows = await api("GET", `/api/throws?machine_id=${encodeURIComponent(state.machineId)}&limit=10`); } catch (e) { return; }
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

// --- wiring -----------------------------------------------------------------------------------------
async function setTypedTarget(e) {
  e.preventDefault();
  const x = parseFloat($("target-x").value), y = parseFloat($("target-y").value);
  if (!Number.isFinite(x) || !Number.isFinite(y)) { setStatus("Type x and y in metres.", true); return; }
  try { await putConsole({ target: [x, y, 0] }); } catch (err) { setStatus(err.message, true); }
}

function wireLive() {
  Live.on("machine", onMachineEvent);
  Live.on("console", applyConsole);
  Live.on("throw", (ev) => {
    if (ev.machine_id !== state.machineId) return;
    if (ev.throw_id !== state.throwId && ["preparing", "swinging"].includes(ev.phase)) {
      state.throwId = ev.throw_id; state.throwStarted = Date.now() - 1000 * ev.elapsed_s;
      startThrowPanel(ev.throw_id);
    }
    const m = selected();
    if (m) { m.phase = ev.phase; renderState(); }
  });
  Live.on("sample", (s) => { if (s.machine_id === state.machineId && s.throw_id === state.throwId) plots.addSample(s); });
  Live.on("result", (r) => { showResult(r.throw_id); refreshHistory(); });
  Live.on("disconnected", renderState);
  Live.on("resumed", renderState);
  Live.on("connected", async () => {
    try { await api("GET", `/api/consoles/${state.consoleId}`); } catch (e) { await openConsole().catch(() => {}); }
    renderState(); refreshHistory();
  });
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  plots = new ThrowPlots($("plots"));
  plots.attachScrubber($("scrub"), $("scrub-play"), $("scrub-readout"));
  $("throw").addEventListener("click", doThrow);
  $("preview").addEventListener("click", doPreview);
  $("estop").addEventListener("click", doEstop);
  $("estop-reset").addEventListener("click", doEstopReset);
  $("return-ready").addEventListener("click", doReturnToReady);
  document.addEventListener("keydown", (e) => { if (e.key === "Escape" && can("operator")) doEstop(); });
  $("target-form").addEventListener("submit", setTypedTarget);
  $("confirm-clearance").addEventListener("change", updateButtons);
  $("machine").addEventListener("change", (e) => selectMachine(e.target.value));
  for (const r of document.querySelectorAll("input[name=mode]")) {
    r.addEventListener("change", async (e) => {
      state.mode = e.target.value;
      await putConsole({ mode: state.mode }).catch((err) => setStatus(err.message, true));
      renderState();
    });
  }
  try { await openConsole(); } catch (e) { setStatus(`3D view unavailable: ${e.message}`, true); }
  try {
    for (const m of await api("GET", "/api/machines")) {
      if (!state.machines.has(m.id)) state.machines.set(m.id, { machine_id: m.id, state: m.online ? "not_ready" : "offline",
        reason: m.online ? "waiting for live state" : "runtime offline", policies: m.policies, simulated: m.simulated });
    }
  } catch (e) { /* the live stream fills it */ }
  renderMachineList();
  const first = [...state.machines.keys()].sort()[0];
  if (first && !state.machineId) await selectMachine(first);
  wireLive();
  Live.start(state.consoleId);
}

document.addEventListener("DOMContentLoaded", init);
