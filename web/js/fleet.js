// Fleet page: every machine with its one state (live push), policies, last throw and recent
// accuracy; admins roll a policy back (after a confirmation). The page follows /api/live: a
// machine whose policies change (a promotion, a rollback confirmed by its runtime) has its
// rollback targets fetched again, so the page offers only a rollback that is possible now.
"use strict";

const fleet = { rows: new Map(), live: new Map(), targets: new Map() };
const WORDS = { ready: "ready", not_ready: "not ready", throwing: "throwing", estopped: "E-STOPPED", offline: "offline" };

function stateText(id) {
  const s = fleet.live.get(id) || (fleet.rows.has(id) && !fleet.rows.get(id).online
    ? { state: "offline", reason: "runtime not running" } : null);
  if (!s) return ["waiting for live state", "state-unknown"];
  const why = s.reason && s.state !== "ready" ? `: ${s.reason}` : "";
  return [`${WORDS[s.state] || s.state}${s.phase && s.state === "throwing" ? ` (${s.phase})` : ""}${why}`, `state-${s.state}`];
}

function render() {
  const body = $("fleet").querySelector("tbody");
  body.innerHTML = "";
  const ids = [...new Set([...fleet.rows.keys(), ...fleet.live.keys()])].sort();
  $("fleet-empty").hidden = ids.length > 0;
  for (const id of ids) {
    const m = fleet.rows.get(id) || { id, policies: {}, simulated: true };
    const live = fleet.live.get(id);
    const policies = live && Object.keys(live.policies || {}).length ? live.policies : m.policies;
    const tr = body.insertRow();
    tr.dataset.machineId = id;
    const [words, cls] = stateText(id);
    const cells = [id, m.simulated ? "SIMULATED" : "real", words, policies["2d"] || "–", policies["3d"] || "–",
      m.last_throw_at ? `${new Date(m.last_throw_at).toLocaleString()} (${m.current_mode}, ${m.last_throw_status})` : "none yet",
      m.recent_mean_abs_error_m === null || m.recent_mean_abs_error_m === undefined ? "–" : `${fmt(m.recent_mean_abs_error_m, 3)} (${m.recent_throws} throws)`];
    cells.forEach((c, i) => {
      const td = tr.insertCell(); td.textContent = c;
      if (i === 2) { td.className = "state-cell"; const b = document.createElement("span"); b.className = `state-badge ${cls}`; b.textContent = WORDS[cls.slice(6)] || "?"; td.textContent = ""; td.append(b, " ", c.replace(/^[^:]*:?\s*/, "")); }
      if (i === 3) td.className = "policy-2d";
    });
    const td = tr.insertCell();
    td.dataset.role = "admin"; td.hidden = !can("admin");
    const targets = fleet.targets.get(id) || {};
    for (const mode of ["2d", "3d"]) {
      const prev = targets[mode];
      if (!policies[mode] || !prev || prev.name === policies[mode]) continue; // only where there is another version to go back to
      const b = document.createElement("button");
      b.type = "button"; b.textContent = `${mode}: roll back to ${prev.name}`; b.className = `rollback-${mode}`;
      b.addEventListener("click", () => rollback(id, mode, policies[mode], prev.name));
      td.appendChild(b);
    }
    if (!td.childNodes.length) td.textContent = "nothing to roll back to";
  }
}

async function rollback(id, mode, current, previous) {
  const ok = await confirmAction(`Roll back ${id}?`, `${id} runs ${current} for ${mode}. Roll back to ${previous}, the policy it ran before? ` +
    "The runtime loads it between throws.", "Roll back");
  if (!ok) { $("fleet-status").textContent = "Rollback cancelled."; return; }
  try {
    const d = await api("POST", "/api/policies/rollback", { machine_id: id, mode });
    $("fleet-status").textContent = `Rolling ${id} back to ${d.policy_version}: ${d.status} (the state above updates when the runtime confirms).`;
  } catch (e) { $("fleet-status").textContent = e.message; }
  loadFleet();
}

async function loadFleet() {
  try { for (const m of await api("GET", "/api/machines")) fleet.rows.set(m.id, m); } catch (e) { return; }
  if (can("admin")) {
    await Promise.all([...fleet.rows.keys()].map((id) => api("GET", `/api/policies/rollback-targets?machine_id=${encodeURIComponent(id)}`)
      .then((t) => fleet.targets.set(id, t)).catch(() => {})));
  }
  render();
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  Live.on("machine", (s) => {
    const before = fleet.live.get(s.machine_id);
    fleet.live.set(s.machine_id, s);
    if (before && JSON.stringify(before.policies) !== JSON.stringify(s.policies)) loadFleet(); // its rollback targets moved
    else render();
  });
  Live.on("job", (j) => { if (j && j.kind !== "preview" && ["done", "failed"].includes(j.status)) loadFleet(); });
  Live.on("result", loadFleet);
  Live.on("connected", loadFleet);
  await loadFleet();
  Live.start();
});
