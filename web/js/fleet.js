// Fleet page: every machine with its one state (live push), policies, last throw and recent
// accuracy, the server whose commands its runtime obeys (its lease) and the results its runtime
// could not deliver; admins roll a policy back and operators take a machine over from another
// server (each after a confirmation whose Cancel has the focus). The page follows /api/live: a
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
    const lease = live && live.state !== "offline" ? live : m; // the live state is newer than the last GET
    const tr = body.insertRow();
    tr.dataset.machineId = id;
    const [words, cls] = stateText(id);
    const cells = [id, m.simulated ? "SIMULATED" : "real", words, policies["2d"] || "–", policies["3d"] || "–",
      m.last_throw_at ? `${new Date(m.last_throw_at).toLocaleString()} (${m.current_mode}, ${m.last_throw_status})` : "none yet",
      m.recent_mean_abs_error_m === null || m.recent_mean_abs_error_m === undefined ? "–" : `${fmt(m.recent_mean_abs_error_m, 3)} (${m.recent_throws} throws)`];
    cells.push(leaseText(lease), lease.undeliverable_results === null || lease.undeliverable_results === undefined ? "–"
      : String(lease.undeliverable_results));
    cells.forEach((c, i) => {
      const td = tr.insertCell(); td.textContent = c;
      if (i === 2) { td.className = "state-cell"; const b = document.createElement("span"); b.className = `state-badge ${cls}`; b.textContent = WORDS[cls.slice(6)] || "?"; td.textContent = ""; td.append(b, " ", c.replace(/^[^:]*:?\s*/, "")); }
      if (i === 3) td.className = "policy-2d";
      if (i === 7) { td.className = "lease"; if (lease.lease_held_here === false && can("operator")) td.append(" ", takeOverButton(id, lease.lease_holder)); }
      if (i === 8) { td.className = "undeliverable"; if (lease.undeliverable_results > 0) td.classList.add("warn"); }
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

function leaseText(m) {
  if (m.lease_held_here === true) return "this server";
  if (m.lease_held_here === false) return `another server: ${m.lease_holder || "(unnamed)"}`;
  return m.online ? "nobody (the next command takes it)" : "–";
}

function takeOverButton(id, holder) {
  const b = document.createElement("button");
  b.type = "button"; b.textContent = "Take over"; b.className = "take-over";
  b.addEventListener("click", () => takeOver(id, holder));
  return b;
}

async function takeOver(id, holder) {
  const ok = await confirmAction(`Take ${id} over?`, `${id} obeys server ${holder || "(unnamed)"} now. Taking it over makes ` +
    `${id} obey this server and refuse that one's commands (throws, resets, moves; its E-STOP still works). ` +
    "The runtime refuses while a throw runs.", "Take over");
  if (!ok) { $("fleet-status").textContent = "Takeover cancelled."; return; }
  try {
    const d = await api("POST", `/api/machines/${encodeURIComponent(id)}/lease/takeover`);
    $("fleet-status").textContent = `${id} is commanded by this server now (${d.holder}).`;
  } catch (e) { $("fleet-status").textContent = e.message; }
  loadFleet();
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

const newestLoad = latestOnly(); // live events ask again: only the newest answer draws

async function loadFleet() {
  const mine = newestLoad();
  let rows;
  try { rows = await api("GET", "/api/machines"); } catch (e) { return; }
  if (!mine()) return; // an older answer landing late would draw older rows over newer ones
  for (const m of rows) fleet.rows.set(m.id, m);
  if (can("admin")) {
    await Promise.all([...fleet.rows.keys()].map((id) => api("GET", `/api/policies/rollback-targets?machine_id=${encodeURIComponent(id)}`)
      .then((t) => { if (mine()) fleet.targets.set(id, t); }).catch(() => {})));
  }
  if (mine()) render();
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  Live.on("machine", (s) => {
    const before = fleet.live.get(s.machine_id);
    fleet.live.set(s.machine_id, s);
    const moved = before && (JSON.stringify(before.policies) !== JSON.stringify(s.policies) // its rollback targets moved
      || before.lease_holder !== s.lease_holder || before.undeliverable_results !== s.undeliverable_results); // or its lease
    if (moved) loadFleet();
    else render();
  });
  Live.on("job", (j) => { if (j && j.kind !== "preview" && ["done", "failed"].includes(j.status)) loadFleet(); });
  Live.on("result", loadFleet);
  Live.on("deployment", loadFleet); // a promotion confirmed (or refused): the rollback target moved
  Live.on("connected", loadFleet);
  await loadFleet();
  Live.start();
});
