// Throw history: server-side filters, sorting and pagination; per-throw preview vs actual,
// telemetry download, the recorded plots with a timeline that drives this page's own 3D view (the
// machine posed from the recording at the cursor's time: play, pause, seek and speed move both).
"use strict";

const FILTERS = ["machine_id", "policy_version", "mode", "status", "min_distance_m", "max_distance_m", "since", "until"];
const hist = { sort: "requested_at", order: "desc", limit: 25, offset: 0, total: 0, shown: new Set(), detail: null };
const newestLoad = latestOnly(), newestDetail = latestOnly(); // only the newest answer draws (quick clicks, results)

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
  const p = filterParams(), mine = newestLoad();
  $("csv").href = `/api/throws/export.csv?${p}`;
  p.set("sort", hist.sort); p.set("order", hist.order); p.set("limit", hist.limit); p.set("offset", hist.offset);
  const res = await fetch(`/api/throws?${p}`);
  if (res.status === 401) { toLogIn(); return; }
  const rows = await res.json().catch(() => null);
  if (!mine()) return; // a newer request (another page, sort or filter) is on its way
  if (!res.ok) { $("page-info").textContent = responseError(res, rows).message; return; }
  hist.total = parseInt(res.headers.get("X-Total-Count") || "0", 10);
  $("throws-empty").hidden = hist.total > 0;
  const body = $("throws").querySelector("tbody");
  body.innerHTML = "";
  hist.shown = new Set(rows.map((t) => t.id));
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

// --- the 3D replay: this page's own console (server.console.scene), posed from the recording at the plots' time ---
const replay3d = { consoleId: null, throwId: null, busy: false, pending: null, unavailable: "" };

/** Open this page's console and its 3D view once; false (with the reason shown) when there is none. */
async function open3d() {
  if (replay3d.consoleId) return true;
  if (replay3d.unavailable) return false;
  try {
    const c = await api("POST", "/api/consoles");
    replay3d.consoleId = c.console_id;
    embedViser($("viser"), c);
    return true;
  } catch (e) {
    replay3d.unavailable = e.message;
    return false;
  }
}

function showShown(r) {
  const fig = $("replay-view");
  fig.dataset.throwId = r.throw_id;
  fig.dataset.shownT = r.t_s.toFixed(3);
  $("replay-3d").textContent = `3D view: throw ${r.throw_id.slice(0, 8)} at t = ${fmt(r.t_s)} s of ${fmt(r.duration_s)} s, the time of the plots' cursor.`;
}

/** Pose the 3D view at ``t`` (s): one request at a time, the newest time wins. */
function seek3d(t) {
  if (!replay3d.consoleId || !replay3d.throwId) return;
  replay3d.pending = t;
  if (replay3d.busy) return;
  replay3d.busy = true;
  (async () => {
    while (replay3d.pending !== null) {
      const want = replay3d.pending, throwId = replay3d.throwId;
      replay3d.pending = null;
      try {
        const c = await api("PUT", `/api/consoles/${replay3d.consoleId}/replay`, { throw_id: throwId, t_s: want });
        if (c.replay && c.replay.throw_id === replay3d.throwId) showShown(c.replay);
      } catch (e) {
        $("replay-3d").textContent = `The 3D view cannot replay this throw. ${e.message}`;
      }
    }
    replay3d.busy = false;
  })();
}

/** Show the 3D replay of throw ``id`` (with telemetry) at the start of its recording. */
async function start3d(id) {
  const fig = $("replay-view");
  fig.hidden = false;
  replay3d.throwId = id;
  delete fig.dataset.shownT;
  if (!(await open3d())) {
    $("viser").hidden = true;
    $("replay-3d").textContent = `No 3D replay here: ${replay3d.unavailable}`;
    return;
  }
  seek3d(0);
}

async function showDetail(id) {
  const mine = newestDetail();
  const t = await api("GET", `/api/throws/${id}`);
  if (!mine()) return;
  hist.detail = id;
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
  if (!plots) {
    plots = new ThrowPlots($("d-plots"));
    plots.attachScrubber($("scrub"), $("scrub-play"), $("scrub-readout"));
    plots.onScrub = (time) => seek3d(time); // play, pause and seek move the 3D view with the plots
  }
  if (!t.telemetry_url) {
    plots.clear();
    replay3d.throwId = null;
    $("replay-view").hidden = true;
    return;
  }
  await start3d(id);
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
  // a throw shown here that ends (its result stored, or closed as lost) is read again: a running
  // throw never stays "requested" on this page; new throws wait for the operator's next query
  Live.on("result", (r) => {
    if (hist.shown.has(r.throw_id)) load();
    if (hist.detail === r.throw_id) showDetail(r.throw_id);
  });
  await load();
  if (q.get("throw")) showDetail(q.get("throw"));
}

document.addEventListener("DOMContentLoaded", init);
