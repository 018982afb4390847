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

const BIN_HALF_M = 0.25; // the server's distance bins are 0.5 m wide (server.db.aggregates.DISTANCE_BIN_M)

/** Nice tick values covering [lo, hi]. */
function ticks(lo, hi, n = 5) {
  const raw = (hi - lo) / n, mag = 10 ** Math.floor(Math.log10(raw || 1));
  const step = [1, 2, 2.5, 5, 10].map((k) => k * mag).find((k) => k >= raw) || raw;
  const out = [];
  for (let v = Math.ceil(lo / step) * step; v <= hi + 1e-9; v += step) out.push(Math.abs(v) < 1e-12 ? 0 : v);
  return out;
}

/** An SVG chart in pixels with labelled axes: returns {svg, X, Y} (data -> px). */
function axes(parent, { xlo, xhi, ylo, yhi, xlabel, ylabel, title, cls, key }) {
  const W = 340, H = 280, L = 52, R = 10, T = 26, B = 40;
  const svg = el("svg", { viewBox: `0 0 ${W} ${H}`, width: W, height: H, class: `plot ${cls}`, role: "img", "aria-label": title }, parent);
  if (key) svg.setAttribute("data-key", key);
  const X = (v) => L + ((v - xlo) / (xhi - xlo)) * (W - L - R);
  const Y = (v) => H - B - ((v - ylo) / (yhi - ylo)) * (H - T - B);
  el("text", { x: L, y: 16, class: "title" }, svg).textContent = title;
  for (const v of ticks(xlo, xhi)) {
    el("line", { x1: X(v), y1: T, x2: X(v), y2: H - B, class: "grid" }, svg);
    el("text", { x: X(v), y: H - B + 14, class: "tick", "text-anchor": "middle" }, svg).textContent = +v.toFixed(2);
  }
  for (const v of ticks(ylo, yhi)) {
    el("line", { x1: L, y1: Y(v), x2: W - R, y2: Y(v), class: "grid" }, svg);
    el("text", { x: L - 4, y: Y(v) + 4, class: "tick", "text-anchor": "end" }, svg).textContent = +v.toFixed(2);
  }
  el("rect", { x: L, y: T, width: W - L - R, height: H - T - B, class: "frame" }, svg);
  el("text", { x: (L + W - R) / 2, y: H - 6, class: "label", "text-anchor": "middle" }, svg).textContent = xlabel;
  el("text", { x: 12, y: (T + H - B) / 2, class: "label", "text-anchor": "middle", transform: `rotate(-90 12 ${(T + H - B) / 2})` }, svg).textContent = ylabel;
  return { svg, X, Y };
}

function figure(key, groups) {
  const box = document.createElement("div");
  box.className = "figure";
  const h = document.createElement("h3");
  h.textContent = key;
  box.appendChild(h);
  // downrange error against the target distance: each throw (newest, dots), bias ± 1σ per bin
  const ds = groups.map((g) => g.target_distance_m);
  const errs = groups.flatMap((g) => g.errors_m.map(([dn]) => dn));
  const spread = Math.max(0.2, ...errs.map(Math.abs), ...groups.map((g) => Math.abs(g.bias_m) + g.sigma_downrange_m));
  const a = axes(box, { xlo: Math.min(...ds) - 0.5, xhi: Math.max(...ds) + 0.5, ylo: -spread * 1.1, yhi: spread * 1.1,
    xlabel: "target distance [m]", ylabel: "downrange error [m]", title: "Downrange error by target distance", cls: "acc-plot", key });
  el("line", { x1: a.X(Math.min(...ds) - 0.5), y1: a.Y(0), x2: a.X(Math.max(...ds) + 0.5), y2: a.Y(0), class: "diag" }, a.svg);
  for (const g of groups) {
    const x = a.X(g.target_distance_m);
    g.errors_m.forEach(([dn], i) => el("circle", { cx: x - 8 + (i % 5) * 4, cy: a.Y(dn), r: 2, class: "pt" }, a.svg));
    el("line", { x1: x + 10, y1: a.Y(g.bias_m - g.sigma_downrange_m), x2: x + 10, y2: a.Y(g.bias_m + g.sigma_downrange_m), class: "bar" }, a.svg);
    el("circle", { cx: x + 10, cy: a.Y(g.bias_m), r: 4, class: "mean" }, a.svg);
  }
  // the errors on the ground with their 1σ ellipses, all distances overlaid (downrange up, crossrange left)
  const lim = Math.max(0.3, ...groups.flatMap((g) => g.errors_m.flat().map(Math.abs))) * 1.15;
  const b = axes(box, { xlo: -lim, xhi: lim, ylo: -lim, yhi: lim, xlabel: "crossrange error [m] (left +)", ylabel: "downrange error [m]",
    title: "Impacts around the target", cls: "err-plot" });
  for (const g of groups) {
    for (const [dn, cr] of g.errors_m) el("circle", { cx: b.X(-cr), cy: b.Y(dn), r: 2, class: "pt" }, b.svg);
    if (g.ellipse) el("polyline", { points: g.ellipse.outline_m.map(([dn, cr]) => `${b.X(-cr)},${b.Y(dn)}`).join(" "), class: "ell" }, b.svg);
  }
  el("circle", { cx: b.X(0), cy: b.Y(0), r: 4, class: "target" }, b.svg);
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
    [g.mode, g.policy_version, `${fmt(g.target_distance_m - BIN_HALF_M)}–${fmt(g.target_distance_m + BIN_HALF_M)}`, g.n, fmt(g.bias_m),
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
