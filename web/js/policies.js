// Policy versions: upload (admin), twin evaluation (a table per version with the paper's figure:
// mean impact with 1 sigma against the target distance), promote to machines and roll back (both
// confirmed first), compare. Which version is active on which machine comes from live push.
"use strict";

let machineIds = [];
const active = new Map(); // machine id -> {mode: version}, from live machine states
let policyRows = [];

function evalSummary(p) {
  if (p.evaluation_status !== "done") return p.evaluation_status === "failed" ? `failed: ${(p.metrics || {}).error || "?"}` : (p.evaluation_status || "not evaluated");
  const t = p.metrics.targets, ok = t.reduce((a, x) => a + x.landed, 0), n = t.reduce((a, x) => a + x.throws, 0);
  return `${ok}/${n} landed over ${t.length} targets (details below)`;
}

function activeOn(p) {
  const on = [...active.entries()].filter(([, pol]) => pol[p.mode] === p.name).map(([id]) => id);
  return on.length ? `active on ${on.join(", ")}` : "not active";
}

/** The twin evaluation of ``p`` as a table and the paper's figure (uPlot). */
function showEvaluation(p) {
  const box = $("evaluation");
  box.hidden = false;
  $("ev-title").textContent = `${p.name} (${p.mode}): twin evaluation, ${p.metrics.throws_per_target} throws per target, ${p.metrics.profile} profile`;
  const body = $("ev-table").querySelector("tbody");
  body.innerHTML = "";
  for (const t of p.metrics.targets) {
    const tr = body.insertRow();
    [fmt(t.target_m, 1), `${t.landed}/${t.throws}`, fmt(t.mean_impact_m), fmt(t.bias_m), fmt(t.sigma_downrange_m, 3),
      fmt(t.sigma_crossrange_m, 3), Object.entries(t.failures || {}).map(([k, v]) => `${k} ×${v}`).join(", ") || "–"]
      .forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i < 6) td.className = "num"; });
  }
  const fig = $("ev-figure");
  fig.innerHTML = "";
  const xs = p.metrics.targets.map((t) => t.target_m), mean = p.metrics.targets.map((t) => t.mean_impact_m);
  const sd = p.metrics.targets.map((t) => t.sigma_downrange_m || 0);
  const w = Math.min(560, fig.clientWidth || 560);
  new uPlot({
    width: w, height: 260, scales: { x: { time: false } },
    axes: [{ label: "target distance [m]", stroke: "#333" }, { label: "impact distance [m]", stroke: "#333", size: 50 }],
    series: [{ label: "target [m]" },
      { label: "ideal", stroke: "#777", dash: [4, 4], points: { show: false } },
      { label: "mean impact", stroke: "#1f5fbf", width: 2, points: { show: true, size: 8, fill: "#1f5fbf" } },
      { label: "+1σ", stroke: "#1f5fbf", dash: [2, 3], points: { show: false } },
      { label: "-1σ", stroke: "#1f5fbf", dash: [2, 3], points: { show: false } }],
  }, [xs, xs, mean, mean.map((m, i) => (m === null ? null : m + sd[i])), mean.map((m, i) => (m === null ? null : m - sd[i]))], fig);
}

const newestLoad = latestOnly(); // machine and job events ask again: only the newest answer draws

async function loadPolicies() {
  const mine = newestLoad();
  let ps, ids;
  try { ps = await api("GET", "/api/policies"); ids = (await api("GET", "/api/machines")).map((m) => m.id); } catch (e) { return; }
  if (!mine()) return; // an older answer: a newer request is on its way
  machineIds = ids;
  policyRows = ps;
  $("policies-empty").hidden = ps.length > 0;
  const body = $("policies").querySelector("tbody");
  const checked = new Set([...document.querySelectorAll(".cmp:checked")].map((c) => c.value));
  body.innerHTML = "";
  for (const p of ps) {
    const tr = body.insertRow();
    tr.dataset.policyId = p.id;
    const cb = document.createElement("input");
    cb.type = "checkbox"; cb.className = "cmp"; cb.value = p.id; cb.checked = checked.has(String(p.id));
    cb.setAttribute("aria-label", `compare ${p.name}`);
    tr.insertCell().appendChild(cb);
    [p.id, p.name, p.mode, p.sha256.slice(0, 12) + "…", p.target_range_m ? p.target_range_m.join("–") : "–",
      `${new Date(p.created_at).toLocaleString()} ${p.uploaded_by || ""}`, activeOn(p), evalSummary(p)]
      .forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i === 7) td.className = "eval"; if (i === 6) td.className = "active-on"; });
    if (p.evaluation_status === "done") {
      const b = document.createElement("button");
      b.type = "button"; b.textContent = "Show evaluation"; b.className = "show-eval";
      b.addEventListener("click", () => showEvaluation(p));
      tr.cells[7].append(" ", b);
    }
    if (can("admin") && p.has_file && !["pending", "running"].includes(p.evaluation_status)) {
      const b = document.createElement("button"); // any version can be evaluated (again), deployed ones too
      b.type = "button"; b.textContent = p.evaluation_status === "done" ? "Evaluate again" : "Evaluate"; b.className = "evaluate";
      b.addEventListener("click", async () => {
        b.disabled = true;
        try {
          await api("POST", `/api/policies/${p.id}/evaluate`);
          $("p-status").textContent = `${p.name}: twin evaluation started; the table updates when it is done.`; $("p-status").className = "";
          loadPolicies();
        } catch (e) { $("p-status").textContent = `Not started: ${e.message}`; $("p-status").className = "error"; b.disabled = false; }
      });
      tr.cells[7].append(" ", b);
    }
    const td = tr.insertCell();
    td.dataset.role = "admin"; td.hidden = !can("admin");
    if (p.has_file) {
      const sel = document.createElement("select");
      sel.className = "promote-target";
      for (const id of machineIds) sel.add(new Option(id, id));
      const b = document.createElement("button");
      b.type = "button"; b.textContent = "Promote"; b.className = "promote";
      sel.setAttribute("aria-label", `machine to promote ${p.name} to`);
      b.addEventListener("click", async () => {
        const ok = await confirmAction(`Promote ${p.name}?`, `${sel.value} will run ${p.name} for every ${p.mode} throw from ` +
          "its next throw on. You can roll back from the Fleet page.", "Promote");
        if (!ok) { $("p-status").textContent = "Promotion cancelled."; $("p-status").className = ""; return; }
        try {
          const deps = await api("POST", `/api/policies/${p.id}/promote`, { machine_ids: [sel.value] });
          $("p-status").textContent = deps.map((d) => `${d.machine_id}: ${d.status}${d.reason ? ` (${d.reason})` : ""}`).join("; ") +
            " · the Active column changes when the runtime confirms.";
          $("p-status").className = deps.some((d) => d.status === "failed") ? "error" : "";
        } catch (e) { $("p-status").textContent = e.message; $("p-status").className = "error"; }
        loadPolicies(); // what the rows offer follows what the server now holds
      });
      td.append(sel, b);
    }
  }
}

async function doUpload(e) {
  e.preventDefault();
  $("p-status").textContent = "uploading…"; $("p-status").className = "";
  try {
    const p = await api("POST", "/api/policies", new FormData($("upload")), true);
    $("p-status").textContent = `accepted: ${p.name} (id ${p.id}); twin evaluation ${p.evaluation_status}`;
    loadPolicies();
  } catch (err) {
    $("p-status").textContent = `Rejected: ${err.message}`; $("p-status").className = "error";
  }
}

async function doCompare() {
  const ids = [...document.querySelectorAll(".cmp:checked")].map((c) => `ids=${c.value}`).join("&");
  if (!ids) return;
  const rows = await api("GET", `/api/policies/compare?${ids}`);
  $("comparison").querySelector("thead").innerHTML = "<tr><th>version</th><th>target [m]</th><th>twin: bias / σ down [m]</th><th>logged: n, bias / σ down [m]</th></tr>";
  const body = $("comparison").querySelector("tbody");
  body.innerHTML = "";
  for (const v of rows) {
    const ds = [...new Set([...v.twin.map((t) => t.target_m), ...v.logged.map((g) => g.target_distance_m)])].sort((a, b) => a - b);
    for (const d of ds) {
      const t = v.twin.find((x) => x.target_m === d), g = v.logged.find((x) => x.target_distance_m === d);
      const tr = body.insertRow();
      [v.name, fmt(d, 1), t ? `${fmt(t.bias_m)} / ${fmt(t.sigma_downrange_m, 3)}` : "–",
        g ? `${g.n}, ${fmt(g.bias_m)} / ${fmt(g.sigma_downrange_m, 3)}` : "–"].forEach((c) => { tr.insertCell().textContent = c; });
    }
  }
}

function renderActive() {
  for (const tr of $("policies").querySelectorAll("tbody tr")) {
    const p = policyRows.find((x) => String(x.id) === tr.dataset.policyId);
    if (p) tr.querySelector(".active-on").textContent = activeOn(p);
  }
}

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  $("upload").addEventListener("submit", doUpload);
  $("compare").addEventListener("click", doCompare);
  Live.on("machine", (m) => {
    const before = JSON.stringify(active.get(m.machine_id) || {});
    if (m.state !== "offline") active.set(m.machine_id, m.policies || {}); else active.delete(m.machine_id);
    if (before !== JSON.stringify(active.get(m.machine_id) || {})) { renderActive(); loadPolicies(); }
  });
  // an evaluation (or any job about policies) that ends changes a row: fetch the rows again, so no
  // row says "pending" after its worker finished and every button offered is possible now
  Live.on("job", (j) => {
    if (!j || j.kind === "preview") return;
    if (["done", "failed", "cancelled"].includes(j.status)) { loadPolicies(); return; }
    // an evaluation running (its progress events) on a row drawn as not running yet: the row changed
    const p = j.kind === "evaluation" && j.status === "running" && policyRows.find((x) => String(x.id) === j.subject);
    if (p && p.evaluation_status !== "running") loadPolicies();
  });
  Live.on("connected", loadPolicies);
  await loadPolicies();
  Live.start();
});
