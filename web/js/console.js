// Slinger operator console: talks to the JSON API only (see /docs).
// The 3D view is viser, served on its own port and embedded in an iframe; a click on the ground
// there sets the server-side target, which this page reads back from GET /api/scene.
"use strict";

const state = { machines: [], machineId: null, mode: "2d", target: null, viserPort: null, lastThrowId: null };

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

async function refreshScene() {
  try {
    const s = await api("GET", "/api/scene");
    if (s.viser_port && s.viser_port !== state.viserPort) {
      state.viserPort = s.viser_port;
      $("viser").src = `${location.protocol}//${location.hostname}:${s.viser_port}/`;
    }
    state.target = s.target;
    if (s.target) {
      const d = Math.hypot(s.target[0], s.target[1]);
      $("target").textContent = `x ${fmt(s.target[0])}  y ${fmt(s.target[1])}  z ${fmt(s.target[2])} m  (${fmt(d, 1)} m from the turn axis)`;
    }
    updateButton();
  } catch (e) { /* server restarting: keep polling */ }
}

async function refreshMachines() {
  try {
    state.machines = await api("GET", "/api/machines");
  } catch (e) { return; }
  const sel = $("machine");
  const ids = state.machines.map((m) => m.id);
  if (sel.options.length !== ids.length || [...sel.options].some((o, i) => o.value !== ids[i])) {
    sel.innerHTML = "";
    for (const id of ids) sel.add(new Option(id, id));
    if (!ids.includes(state.machineId)) state.machineId = ids[0] || null;
    sel.value = state.machineId || "";
    if (state.machineId) api("PUT", "/api/scene", { machine_id: state.machineId }).catch(() => {});
  }
  const m = state.machines.find((x) => x.id === state.machineId);
  const kind = $("machine-kind");
  kind.hidden = !m;
  if (m) {
    kind.textContent = m.simulated ? "SIMULATED machine" : "real machine";
    kind.className = m.simulated ? "badge sim" : "badge";
    const pol = m.policies[state.mode];
    $("machine-online").textContent = m.online ? `online · ${state.mode} policy ${pol || "none"}` : "runtime offline";
    $("machine-online").className = `badge ${m.online ? "online" : "offline"}`;
  }
  updateButton();
}

function updateButton() {
  const m = state.machines.find((x) => x.id === state.machineId);
  $("throw").disabled = !(m && m.online && state.target);
}

async function refreshHistory() {
  if (!state.machineId) return;
  let rows;
  try {
    rows = await api("GET", `/api/throws?machine_id=${encodeURIComponent(state.machineId)}&limit=30`);
  } catch (e) { return; }
  const body = $("history").querySelector("tbody");
  body.innerHTML = "";
  for (const t of rows) {
    const tr = body.insertRow();
    tr.dataset.throwId = t.id;
    const cells = [
      new Date(t.requested_at).toLocaleTimeString(), t.mode, fmtVec(t.target), fmtVec(t.impact),
      fmt(t.downrange_error_m), fmt(t.crossrange_error_m), t.policy_version || "–", t.status,
    ];
    cells.forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i === 7) td.className = `status-${t.status}`; });
    if (t.failure_reason) tr.title = t.failure_reason;
    if (t.id === state.lastThrowId) {
      const done = ["landed", "failed", "aborted"].includes(t.status);
      setStatus(`Throw ${t.id.slice(0, 8)}: ${t.status}` + (t.impact ? `, impact ${fmtVec(t.impact)} m, downrange ${fmt(t.downrange_error_m)} m, crossrange ${fmt(t.crossrange_error_m)} m` : "") + (t.failure_reason ? ` (${t.failure_reason})` : ""), t.status === "failed");
      if (done) state.lastThrowId = null;
    }
  }
}

async function doThrow() {
  $("throw").disabled = true;
  setStatus("Sending throw…");
  try {
    const r = await api("POST", "/api/throws", { machine_id: state.machineId, mode: state.mode, target: state.target });
    state.lastThrowId = r.id;
    setStatus(`Throw ${r.id.slice(0, 8)} accepted (policy ${r.policy_version || "?"})`);
    refreshHistory();
  } catch (e) {
    setStatus(`Refused: ${e.message}`, true);
  } finally {
    updateButton();
  }
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  $("throw").addEventListener("click", doThrow);
  $("machine").addEventListener("change", (e) => {
    state.machineId = e.target.value;
    api("PUT", "/api/scene", { machine_id: state.machineId }).catch(() => {});
    refreshHistory();
  });
  for (const r of document.querySelectorAll("input[name=mode]")) {
    r.addEventListener("change", (e) => {
      state.mode = e.target.value;
      api("PUT", "/api/scene", { mode: state.mode }).catch(() => {});
      refreshMachines();
    });
  }
  refreshScene(); refreshMachines(); refreshHistory();
  setInterval(refreshScene, 500);
  setInterval(refreshMachines, 2000);
  setInterval(refreshHistory, 1500);
}

document.addEventListener("DOMContentLoaded", init);
