// Policy versions: upload (admin), twin evaluation, promote to machines, compare.
"use strict";

let machineIds = [];

function evalText(p) {
  if (p.evaluation_status !== "done") return p.evaluation_status || "–";
  return p.metrics.targets.map((t) => `${fmt(t.target_m, 1)} m: ${t.landed}/${t.throws} landed, bias ${fmt(t.bias_m)}, σ ${fmt(t.sigma_downrange_m, 3)}`).join("; ");
}

async function loadPolicies() {
  let ps;
  try { ps = await api("GET", "/api/policies"); machineIds = (await api("GET", "/api/machines")).map((m) => m.id); } catch (e) { return; }
  const body = $("policies").querySelector("tbody");
  const checked = new Set([...document.querySelectorAll(".cmp:checked")].map((c) => c.value));
  body.innerHTML = "";
  for (const p of ps) {
    const tr = body.insertRow();
    tr.dataset.policyId = p.id;
    const cb = document.createElement("input");
    cb.type = "checkbox"; cb.className = "cmp"; cb.value = p.id; cb.checked = checked.has(String(p.id));
    tr.insertCell().appendChild(cb);
    [p.id, p.name, p.mode, p.sha256.slice(0, 12) + "…", p.target_range_m ? p.target_range_m.join("–") : "–",
      `${new Date(p.created_at).toLocaleString()} ${p.uploaded_by || ""}`, evalText(p)]
      .forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i === 6) td.className = "eval"; });
    const td = tr.insertCell();
    td.dataset.role = "admin"; td.hidden = !can("admin");
    if (p.has_file) {
      const sel = document.createElement("select");
      sel.className = "promote-target";
      for (const id of machineIds) sel.add(new Option(id, id));
      const b = document.createElement("button");
      b.textContent = "Promote"; b.className = "promote";
      b.addEventListener("click", async () => {
        try {
          const deps = await api("POST", `/api/policies/${p.id}/promote`, { machine_ids: [sel.value] });
          $("p-status").textContent = deps.map((d) => `${d.machine_id}: ${d.status}${d.reason ? ` (${d.reason})` : ""}`).join("; ");
          $("p-status").className = deps.some((d) => d.status === "failed") ? "error" : "";
        } catch (e) { $("p-status").textContent = e.message; $("p-status").className = "error"; }
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

document.addEventListener("DOMContentLoaded", async () => {
  try { await whoAmI(); } catch (e) { return; }
  $("upload").addEventListener("submit", doUpload);
  $("compare").addEventListener("click", doCompare);
  loadPolicies(); setInterval(loadPolicies, 3000);
});
