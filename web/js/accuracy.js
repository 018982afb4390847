// Accuracy view: GET /api/throws/accuracy (landed throws per mode, policy version, target distance).
"use strict";

const AFILTERS = ["machine_id", "policy_version", "mode", "since", "until"];
const SVGNS = "http://www.w3.org/2000/svg";

function el(name, attrs, parent) {
  const e = document.createElementNS(SVGNS, name);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (parent) parent.appendChild(e);
  return e;
}

function params() {
  const p = new URLSearchParams();
  for (const f of AFILTERS) {
    let v = $(`f-${f}`).value;
    if (!v) continue;
    if (f === "since" || f === "until") v = new Date(v).toISOString();
    p.set(f, v);
  }
  return p;
}

function figure(key, groups) {
  // impact distance vs target distance, mean +- 1 sigma
  const ds = groups.map((g) => g.target_distance_m);
  const lo = Math.min(...ds) - 1, hi = Math.max(...ds) + 1, span = hi - lo;
  const box = document.createElement("div");
  box.className = "figure";
  box.innerHTML = `<h3>${key}</h3>`;
  const svg = el("svg", { viewBox: `0 0 ${span} ${span}`, width: 300, height: 300, class: "plot acc-plot", "data-key": key }, box);
  const Y = (v) => span - (v - lo);
  el("line", { x1: 0, y1: Y(lo), x2: span, y2: Y(hi), class: "diag" }, svg);
  for (const g of groups) {
    const x = g.target_distance_m - lo, m = g.mean_impact_distance_m, s = g.sigma_downrange_m;
    el("line", { x1: x, y1: Y(m - s), x2: x, y2: Y(m + s), class: "bar" }, svg);
    el("circle", { cx: x, cy: Y(m), r: 0.08, class: "mean" }, svg);
  }
  // errors with 1 sigma ellipses, all distances overlaid (downrange up, crossrange left)
  const svg2 = el("svg", { viewBox: "-1.5 -1.5 3 3", width: 300, height: 300, class: "plot err-plot" }, box);
  for (const g of groups) {
    for (const [dn, cr] of g.errors_m) el("circle", { cx: -cr, cy: -dn, r: 0.025, class: "pt" }, svg2);
    if (g.ellipse) el("polyline", { points: g.ellipse.outline_m.map(([dn, cr]) => `${-cr},${-dn}`).join(" "), class: "ell" }, svg2);
  }
  el("text", { x: -1.45, y: -1.3 }, svg2).textContent = "errors: downrange ↑, crossrange ←";
  return box;
}

async function load() {
  const p = params();
  $("csv").href = `/api/throws/export.csv?${p}`;
  const groups = await api("GET", `/api/throws/accuracy?${p}`);
  const byKey = {};
  for (const g of groups) (byKey[`${g.mode} · ${g.policy_version}`] ||= []).push(g);
  $("plots").innerHTML = "";
  for (const [k, gs] of Object.entries(byKey)) $("plots").appendChild(figure(k, gs));
  $("accuracy-empty").hidden = groups.length > 0;
  const body = $("accuracy").querySelector("tbody");
  body.innerHTML = "";
  for (const g of groups) {
    const tr = body.insertRow();
    [g.mode, g.policy_version, fmt(g.target_distance_m, 1), g.n, fmt(g.mean_impact_distance_m), fmt(g.bias_m),
      fmt(g.sigma_downrange_m, 3), fmt(g.sigma_crossrange_m, 3), fmt(g.mean_abs_error_m, 3)]
      .forEach((c) => { tr.insertCell().textContent = c; });
  }
}

async function init() {
  try { await whoAmI(); } catch (e) { return; }
  $("filters").addEventListener("submit", (e) => { e.preventDefault(); load(); });
  load();
}

document.addEventListener("DOMContentLoaded", init);
