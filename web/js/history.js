// Throw history: server-side filters, sorting and pagination; per-throw preview vs actual,
// telemetry download, replay in the 3D view and a side view of the recorded trajectory.
"use strict";

const FILTERS = ["machine_id", "policy_version", "mode", "status", "min_distance_m", "max_distance_m", "since", "until"];
const hist = { sort: "requested_at", order: "desc", limit: 25, offset: 0, total: 0 };

function filterParams() {
  const p = new URLSearchParams();
  for (const f of FILTERS) {
    let v = $(`f-${f}`).value;
    if (!v) continue;
    if (f === "since" || f === "until") v = new Date(v).toISOString();
    p.set(f, v);
  }
  return p;
}

async function load() {
  const p = filterParams();
  $("csv").href = `/api/throws/export.csv?${p}`;
  p.set("sort", hist.sort); p.set("order", hist.order); p.set("limit", hist.limit); p.set("offset", hist.offset);
  const res = await fetch(`/api/throws?${p}`);
  if (res.status === 401) { location.href = "/console/login.html?next=/console/history.html"; return; }
  const rows = await res.json();
  if (!res.ok) { $("page-info").textContent = `error: ${JSON.stringify(rows.detail)}`; return; }
  hist.total = parseInt(res.headers.get("X-Total-Count") || "0", 10);
  $("throws-empty").hidden = hist.total > 0;
  const body = $("throws").querySelector("tbody");
  body.innerHTML = "";
  for (const t of rows) {
    const tr = body.insertRow();
    tr.dataset.throwId = t.id;
    [new Date(t.requested_at).toLocaleString(), t.machine_id, t.mode, t.policy_version || "–", fmt(t.target_distance_m),
      fmt(t.downrange_error_m), fmt(t.crossrange_error_m), fmt(t.duration_s), t.status]
      .forEach((c, i) => { const td = tr.insertCell(); td.textContent = c; if (i === 8) td.className = `status-${t.status}`; });
    tr.addEventListener("click", () => showDetail(t.id));
  }
  const pages = Math.max(1, Math.ceil(hist.total / hist.limit));
  $("page-info").textContent = `page ${Math.floor(hist.offset / hist.limit) + 1} of ${pages} (${hist.total} throws)`;
  $("prev").disabled = hist.offset === 0;
  $("next").disabled = hist.offset + hist.limit >= hist.total;
  for (const th of document.querySelectorAll("th[data-sort]")) {
    th.classList.toggle("sorted", th.dataset.sort === hist.sort);
    th.dataset.order = th.dataset.sort === hist.sort ? hist.order : "";
  }
}

let plots = null;

async function showDetail(id) {
  const t = await api("GET", `/api/throws/${id}`);
  $("detail").hidden = false;
  $("d-id").textContent = `${t.id.slice(0, 8)} · ${t.machine_id} · ${t.mode} · ${t.status}${t.failure_reason ? ` (${t.failure_reason})` : ""}`;
  const p = t.preview || {};
  $("d-pred-down").textContent = fmt(p.downrange_error_m); $("d-act-down").textContent = fmt(t.downrange_error_m);
  $("d-pred-cross").textContent = fmt(p.crossrange_error_m); $("d-act-cross").textContent = fmt(t.crossrange_error_m);
  $("d-pred-impact").textContent = fmtVec(p.impact_m); $("d-act-impact").textContent = fmtVec(t.impact);
  $("d-pred-duration").textContent = fmt(p.duration_s); $("d-act-duration").textContent = fmt(t.duration_s);
  $("mcap").hidden = !t.telemetry_url;
  if (t.telemetry_url) $("mcap").href = t.telemetry_url;
  $("replay").onclick = () => { location.href = `index.html?replay=${encodeURIComponent(id)}`; }; // the 3D view is on the Console page
  $("d-failure").textContent = t.failure_reason ? `${t.status.toUpperCase()}: ${t.failure_reason}` : "";
  $("d-noplot").hidden = !!t.telemetry_url;
  if (!plots) { plots = new ThrowPlots($("d-plots")); plots.attachScrubber($("scrub"), $("scrub-play"), $("scrub-readout")); }
  if (!t.telemetry_url) { plots.clear(); return; }
  const tr = await api("GET", `/api/throws/${id}/trajectory`);
  plots.showTrajectory(tr);
  plots.enableScrubber();
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  $("filters").addEventListener("submit", (e) => { e.preventDefault(); hist.offset = 0; load(); });
  $("prev").addEventListener("click", () => { hist.offset = Math.max(0, hist.offset - hist.limit); load(); });
  $("next").addEventListener("click", () => { hist.offset += hist.limit; load(); });
  for (const th of document.querySelectorAll("th[data-sort]")) {
    th.addEventListener("click", () => {
      if (hist.sort === th.dataset.sort) hist.order = hist.order === "desc" ? "asc" : "desc";
      else { hist.sort = th.dataset.sort; hist.order = "desc"; }
      hist.offset = 0; load();
    });
  }
  const q = new URLSearchParams(location.search);
  for (const f of FILTERS) if (q.get(f) && f !== "since" && f !== "until") $(`f-${f}`).value = q.get(f);
  await load();
  if (q.get("throw")) showDetail(q.get("throw"));
}

document.addEventListener("DOMContentLoaded", init);
