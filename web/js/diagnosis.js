// Diagnosis page: start a run on a machine's stored throws, list runs, show a report.
"use strict";

const pct = (x) => (x === null || x === undefined ? "–" : `${(100 * x).toFixed(0)}%`);
let polling = null;

async function loadRuns() {
  const runs = await api("GET", "/api/diagnosis/runs");
  const body = $("runs").querySelector("tbody");
  body.innerHTML = "";
  for (const r of runs) {
    const tr = document.createElement("tr");
    tr.innerHTML = `<td><a href="#${r.id}">${r.id}</a></td><td>${r.machine_id}</td><td>${r.throws}</td>` +
      `<td class="status-${r.status === "done" ? "landed" : r.status}">${r.status}</td><td>${r.verdict ? r.verdict.text : (r.error || "")}</td>`;
    body.appendChild(tr);
  }
  if (runs.some((r) => r.status === "running") && !polling) polling = setTimeout(() => { polling = null; loadRuns(); }, 3000);
  const want = location.hash.slice(1) || (runs.find((r) => r.status === "done") || {}).id;
  if (want) showRun(want);
}

async function showRun(id) {
  const run = await api("GET", `/api/diagnosis/runs/${id}`);
  if (!run.report) return;
  const rep = run.report;
  $("report").hidden = false;
  $("r-id").textContent = id;
  $("r-verdict").textContent = rep.verdict.text;
  const file = (n) => `/api/diagnosis/runs/${id}/files/${n}`;
  for (const n of ["where", "traces", "which", "how_far"]) $(`img-${n}`).src = file(`${n}.png`);
  $("r-json").href = file("report.json");
  $("r-profile").href = file("profile_fitted.json");
  const w = rep.where.conditioned;
  const chans = Object.entries(w.channels).sort((a, b) => b[1].share - a[1].share).slice(0, 10);
  $("where").querySelector("tbody").innerHTML = chans.map(([c, v]) =>
    `<tr><td>${c}</td><td>${pct(v.share)}</td><td>${fmt(v.rms, 4)} ${v.unit}</td>` +
    ["swing", "release", "flight"].map((p) => `<td>${v.by_phase[p] === undefined ? "–" : fmt(v.by_phase[p], 4)}</td>`).join("") + "</tr>").join("");
  $("phases").textContent = "Share of the gap per phase: " + Object.entries(w.phases).map(([p, s]) => `${p} ${pct(s)}`).join(", ");
  $("which").querySelector("tbody").innerHTML = rep.which.map((r) =>
    `<tr><td>${r.effect}</td><td>${fmt(r.score, 3)}</td><td>${fmt(r.j_test_nominal, 3)} → ${fmt(r.j_test, 3)}</td><td>` +
    Object.entries(r.params).map(([k, v]) => `${k} = ${Number(v).toPrecision(4)}${r.sigma[k] !== undefined ? " ± " + Number(r.sigma[k]).toPrecision(2) : ""}`).join(", ") +
    "</td></tr>").join("");
  const h = rep.how_far;
  $("howfar").textContent = `With ${h.effect}${h.named ? "" : " (best candidate, not named)"}: held-out gap J ${fmt(h.J_before, 3)} → ${fmt(h.J_after, 3)}; ` +
    `impact error ${fmt(h.impact_error_m.predicted_before, 3)} → ${fmt(h.impact_error_m.predicted_after, 3)} m (shrink ${pct(h.impact_gap_shrink)}).`;
  const acc = h.accuracy;
  $("accuracy").querySelector("tbody").innerHTML = Object.keys(acc.observed).sort((a, b) => a - b).map((d) =>
    `<tr><td>${d}</td>` + ["observed", "replayed_nominal", "replayed_fitted"].map((k) => {
      const a = acc[k][d];
      return `<td>${a ? `${fmt(a.mean_downrange_m)} ± ${fmt(a.sigma_downrange_m)}` : "–"}</td>`;
    }).join("") + "</tr>").join("");
}

document.addEventListener("DOMContentLoaded", async () => {
  await whoAmI();
  $("start").addEventListener("submit", async (ev) => {
    ev.preventDefault();
    $("start-msg").textContent = "exporting throws…";
    try {
      const st = await api("POST", "/api/diagnosis/runs", { machine_id: $("machine_id").value, limit: Number($("limit").value) });
      $("start-msg").textContent = `run ${st.id} started on ${st.throws} throws`;
      loadRuns();
    } catch (e) {
      $("start-msg").textContent = e.message;
    }
  });
  window.addEventListener("hashchange", () => showRun(location.hash.slice(1)));
  loadRuns();
});
