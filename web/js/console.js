// Slinger operator console: pick a target (click the 3D view or type it), Preview it in the twin,
// Throw as previewed, E-stop. Talks to the JSON API only (see /docs). The 3D view is viser on its
// own port in an iframe; a click on the ground there sets the server-side target (GET /api/scene).
"use strict";

const state = { machines: [], machineId: null, mode: "2d", target: null, viserPort: null, lastThrowId: null,
  preview: null, previewKey: null, busy: false };

function setStatus(text, isError = false) {
  $("status").textContent = text;
  $("status").className = isError ? "error" : "";
}

const requestKey = () => JSON.stringify([state.machineId, state.mode, state.target]);

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
    updateButtons();
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
    if (state.machineId && can("operator")) api("PUT", "/api/scene", { machine_id: state.machineId }).catch(() => {});
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
  updateButtons();
}

function updateButtons() {
  const m = state.machines.find((x) => x.id === state.machineId);
  const ready = !!(m && m.online && state.target) && !state.busy;
  $("preview").disabled = !ready;
  const previewed = state.preview && state.preview.status === "ok" && state.previewKey === requestKey();
  const confirmed = state.mode !== "3d" || $("confirm-clearance").checked;
  $("throw").disabled = !(ready && previewed && confirmed);
  $("confirm-box").hidden = state.mode !== "3d";
  if (state.preview && state.previewKey !== requestKey()) $("preview-panel").classList.add("stale");
  else $("preview-panel").classList.remove("stale");
}

function showPreview(p) {
  $("preview-panel").hidden = false;
  $("pv-policy").textContent = `${p.policy_version} on ${p.machine_id}, ${p.mode}`;
  if (p.status !== "ok") {
    for (const id of ["pv-down", "pv-cross", "pv-duration", "pv-release", "pv-speeds", "pv-clearance"]) $(id).textContent = "–";
    $("pv-sigma").textContent = "–";
    setStatus(`Preview: the twin's swing failed (${p.reason})`, true);
    return;
  }
  $("pv-down").textContent = `${fmt(p.downrange_error_m)} m`;
  $("pv-cross").textContent = `${fmt(p.crossrange_error_m)} m`;
  $("pv-duration").textContent = `${fmt(p.duration_s)} s (release after ${fmt(p.release_after_s)} s)`;
  const v = p.release_vel_mps;
  $("pv-release").textContent = `${fmt(Math.hypot(v[0], v[1], v[2]))} m/s at ${fmtVec(p.release_pos_m)} m`;
  const sp = p.peak_joint_speeds;
  $("pv-speeds").textContent = Object.entries(sp).map(([k, x]) => `${k} ${fmt(x)}`).join(", ");
  const c = p.clearance;
  $("pv-clearance").textContent = c.inside ? `inside (reach ${fmt(c.max_radius_m, 1)} m of ${fmt(c.radius_m, 1)} m)`
    : `OUTSIDE: ${c.reasons.join(", ")}`;
  $("pv-clearance").className = c.inside ? "ok" : "error";
  // top view around the target: downrange up, crossrange (left positive) to the left
  const t = p.target_m, d = Math.hypot(t[0], t[1]), u = [t[0] / d, t[1] / d];
  const toSvg = (x, y) => { const e = [x - t[0], y - t[1]]; const dn = e[0] * u[0] + e[1] * u[1]; const cr = -e[0] * u[1] + e[1] * u[0]; return [-cr, -dn]; };
  const [ix, iy] = toSvg(p.impact_m[0], p.impact_m[1]);
  $("pv-impact").setAttribute("cx", ix); $("pv-impact").setAttribute("cy", iy);
  if (p.mc && p.mc.ellipse) {
    $("pv-sigma").textContent = `${fmt(p.mc.sigma_downrange_m, 3)} / ${fmt(p.mc.sigma_crossrange_m, 3)} m (${p.mc.rollouts} rollouts)`;
    $("pv-ellipse").setAttribute("points", p.mc.ellipse.outline_m.map(([x, y]) => toSvg(x, y).join(",")).join(" "));
  } else {
    $("pv-sigma").textContent = "computing…";
    $("pv-ellipse").setAttribute("points", "");
  }
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
    if (quick.status === "ok") {
      const full = await api("POST", "/api/previews", body);
      state.preview = full;
      showPreview(full);
      setStatus(`Preview ready: ${fmt(full.downrange_error_m)} m downrange, ${fmt(full.crossrange_error_m)} m crossrange`);
    }
  } catch (e) {
    state.preview = null;
    $("preview-panel").hidden = true;
    setStatus(`Refused: ${e.message}`, true);
  } finally {
    state.busy = false; updateButtons();
  }
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
    tr.addEventListener("click", () => { location.href = `history.html?throw=${t.id}`; });
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
    const body = { machine_id: state.machineId, mode: state.mode, target: state.target, preview_id: state.preview.id };
    if (state.mode === "3d") body.confirm_clearance = $("confirm-clearance").checked;
    const r = await api("POST", "/api/throws", body);
    state.lastThrowId = r.id;
    $("confirm-clearance").checked = false;
    setStatus(`Throw ${r.id.slice(0, 8)} accepted (policy ${r.policy_version || "?"})`);
    refreshHistory();
  } catch (e) {
    setStatus(`Refused: ${e.message}`, true);
  } finally {
    updateButtons();
  }
}

async function doAbort() {
  try {
    const r = await api("POST", `/api/machines/${encodeURIComponent(state.machineId)}/abort`, { reason: "E-stop in the console" });
    setStatus(`STOPPED ${r.machine_id}: valves neutral` + (r.aborted_throw_id ? `, throw ${r.aborted_throw_id.slice(0, 8)} aborted` : ""), true);
  } catch (e) {
    setStatus(`E-stop NOT confirmed: ${e.message}`, true);
  }
}

async function setTypedTarget(e) {
  e.preventDefault();
  const x = parseFloat($("target-x").value), y = parseFloat($("target-y").value);
  if (!Number.isFinite(x) || !Number.isFinite(y)) { setStatus("type x and y in metres", true); return; }
  try { await api("PUT", "/api/scene", { target: [x, y, 0] }); await refreshScene(); } catch (err) { setStatus(err.message, true); }
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  $("throw").addEventListener("click", doThrow);
  $("preview").addEventListener("click", doPreview);
  $("abort").addEventListener("click", doAbort);
  $("target-form").addEventListener("submit", setTypedTarget);
  $("confirm-clearance").addEventListener("change", updateButtons);
  $("machine").addEventListener("change", (e) => {
    state.machineId = e.target.value;
    if (can("operator")) api("PUT", "/api/scene", { machine_id: state.machineId }).catch(() => {});
    refreshHistory();
  });
  for (const r of document.querySelectorAll("input[name=mode]")) {
    r.addEventListener("change", (e) => {
      state.mode = e.target.value;
      if (can("operator")) api("PUT", "/api/scene", { mode: state.mode }).catch(() => {});
      refreshMachines();
    });
  }
  refreshScene(); refreshMachines(); refreshHistory();
  setInterval(refreshScene, 500);
  setInterval(refreshMachines, 2000);
  setInterval(refreshHistory, 1500);
}

document.addEventListener("DOMContentLoaded", init);
