// Plots of one throw with uPlot (web/vendor/uplot, from the npm package): joint velocities with
// their references, valve commands, passive angles (time on x), and the payload path seen from
// the side (distance from the turn axis, height) with release, impact and target marked, next to
// the preview's predicted path. Live during a throw (addSample, from server-sent samples), full
// after it (showTrajectory, GET /api/throws/{id}/trajectory), with a timeline scrubber whose
// cursor time other views follow (onScrub: the History page's 3D replay).
"use strict";

const JOINTS = ["cabin turn", "boom", "dipper", "telescope"];
const COLORS = ["#1f5fbf", "#c2410c", "#15803d", "#7e22ce"];
const PASSIVE = ["gripper pitch", "gripper roll"];

/** A scale range uPlot can always tick: padded, never empty nor non-finite. A zero-width range
 *  (one sample, or a stalled machine repeating its state) made uPlot's axis splits loop until
 *  "Invalid array length". */
function safeRange(_u, min, max) {
  if (!Number.isFinite(min) || !Number.isFinite(max)) return [0, 1];
  const span = max - min;
  if (span < 1e-6 * Math.max(1, Math.abs(min), Math.abs(max))) return [min - 0.5, max + 0.5];
  return [min - 0.05 * span, max + 0.05 * span];
}

function el(tag, attrs = {}, text = "") {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) e.setAttribute(k, v);
  if (text) e.textContent = text;
  return e;
}

class ThrowPlots {
  /** @param {HTMLElement} root container; charts are sized to its width. */
  constructor(root) {
    this.root = root;
    this.charts = {};
    this.data = null;
    this.scrubber = null;
    this.playing = null;
    this.readout = null;
    this.lastWidth = 0;
    this.onScrub = null; // (t [s from the recording's start], sample index): called whenever the cursor moves
    new ResizeObserver(() => { if (Math.abs(this.width() - this.lastWidth) > 4) this.resize(); }).observe(root);
  }

  width() { return Math.max(240, Math.min(this.root.clientWidth - 4, 720)); }

  _chart(key, title, series, scales = {}, mode = 1) {
    const box = el("figure", { class: "chart", "data-chart": key });
    box.appendChild(el("figcaption", {}, title));
    this.root.appendChild(box);
    this.lastWidth = this.width();
    const opts = {
      width: this.lastWidth, height: 150, mode,
      scales: { x: { time: false, range: safeRange }, y: { range: safeRange }, ...scales },
      axes: [{ stroke: "#333", grid: { stroke: "#e5e5e5" } }, { stroke: "#333", grid: { stroke: "#e5e5e5" }, size: 46 }],
      series: [{ label: mode === 2 ? "" : "t [s]" }, ...series],
      legend: { live: mode !== 2 },
      cursor: { drag: { x: false, y: false } },
    };
    const empty = mode === 2 ? [null, ...series.map(() => [[], []])] : [[], ...series.map(() => [])];
    this.charts[key] = new uPlot(opts, empty, box);
    return this.charts[key];
  }

  /** Empty charts for a new throw (live samples follow). */
  reset() {
    for (const c of Object.values(this.charts)) c.destroy();
    this.root.innerHTML = "";
    this.charts = {};
    const line = (label, stroke, dash) => ({ label, stroke, width: 1.6, dash, points: { show: false } });
    this._chart("qd", "Joint velocities [rad/s, m/s]: measured (solid), reference (dashed)",
      [...JOINTS.map((j, i) => line(j, COLORS[i])), ...JOINTS.map((j, i) => line(`${j} ref`, COLORS[i], [5, 4]))]);
    this._chart("u", "Valve commands [-1, 1]", JOINTS.map((j, i) => line(j, COLORS[i])), { y: { range: [-1.05, 1.05] } });
    this._chart("passive", "Passive angles of the hanging gripper [rad]", PASSIVE.map((j, i) => line(j, COLORS[i])));
    const xy = (label, stroke, dash, pts) => ({ label, stroke, width: pts ? 0 : 2, dash, paths: pts ? undefined : uPlot.paths.linear(),
      points: { show: !!pts, size: 9, fill: stroke, stroke }, facets: [{ scale: "x", auto: true }, { scale: "y", auto: true }] });
    this._chart("path", "Payload path, side view: distance from the turn axis [m] → height [m]",
      [xy("recorded", "#b91c1c"), xy("preview", "#c2410c", [6, 4]), xy("release", "#6d28d9", null, true),
        xy("impact", "#b91c1c", null, true), xy("target", "#15803d", null, true)], {}, 2);
    this.live = { t: [], qd: [[], [], [], []], u: [[], [], [], []], p: [[], []], pa: [[], []] };
    this.data = null;
  }

  /** Append a live sample (server.console.live.sample_of) and redraw. */
  addSample(s) {
    if (!this.live) this.reset();
    const L = this.live;
    L.t.push(s.t_s);
    s.qd.forEach((v, i) => L.qd[i].push(v));
    (s.u || [null, null, null, null]).forEach((v, i) => L.u[i].push(v));
    s.passive_rad.forEach((v, i) => L.pa[i].push(v));
    L.p[0].push(Math.hypot(s.p_m[0], s.p_m[1])); L.p[1].push(s.p_m[2]);
    const nulls = L.t.map(() => null);
    this.charts.qd.setData([L.t, ...L.qd, nulls, nulls, nulls, nulls]);
    this.charts.u.setData([L.t, ...L.u]);
    this.charts.passive.setData([L.t, ...L.pa]);
    this.charts.path.setData([null, [L.p[0], L.p[1]], [[], []], [[], []], [[], []], [[], []]]);
  }

  /** The recorded throw (trajectory endpoint) with references, marks and the preview path. */
  showTrajectory(tr) {
    this.reset();
    const t0 = tr.t_s.length ? tr.t_s[0] : 0; // time from the start of the recording
    tr = { ...tr, t_s: tr.t_s.map((x) => x - t0), payload_t_s: tr.payload_t_s.map((x) => x - t0),
      events: (tr.events || []).map((e) => ({ ...e, t_s: e.t_s - t0 })) };
    this.data = tr;
    const t = tr.t_s, col = (rows, i) => rows.map((r) => r[i]);
    const refs = tr.qd_ref.length ? [0, 1, 2, 3].map((i) => col(tr.qd_ref, i)) : [0, 1, 2, 3].map(() => t.map(() => null));
    this.charts.qd.setData([t, ...[0, 1, 2, 3].map((i) => col(tr.qd, i)), ...refs]);
    this.charts.u.setData([t, ...[0, 1, 2, 3].map((i) => (tr.valve_u.length ? col(tr.valve_u, i) : t.map(() => null)))]);
    this.charts.passive.setData([t, col(tr.q, 4), col(tr.q, 5)]);
    const side = (pts) => [pts.map((p) => Math.hypot(p[0], p[1])), pts.map((p) => p[2])];
    const released = tr.payload_path_m.length ? tr.payload_path_m : tr.gripper_path_m;
    const pv = tr.preview && tr.preview.payload_path_m ? side(tr.preview.payload_path_m) : [[], []];
    const relEv = (tr.events || []).find((e) => e.phase === "released");
    let relPt = [[], []];
    if (relEv && tr.payload_t_s.length) {
      const k = tr.payload_t_s.findIndex((x) => x >= relEv.t_s);
      if (k >= 0) relPt = side([tr.payload_path_m[k]]);
    }
    this.charts.path.setData([null, side(released), pv, relPt, tr.impact_m ? side([tr.impact_m]) : [[], []],
      tr.target_m ? side([tr.target_m]) : [[], []]]);
  }

  /** A range input + play button that move the cursor of every chart over the recorded time;
   *  a labelled speed choice (times real time) is added next to the button. */
  attachScrubber(input, playButton, readout) {
    this.scrubber = input; this.readout = readout;
    const label = el("label", { class: "replay-speed" }, "speed ");
    const speed = el("select", { "aria-label": "replay speed" });
    for (const [v, t] of [["0.25", "0.25× real time"], ["0.5", "0.5× real time"], ["1", "1× real time"]]) speed.add(new Option(t, v));
    speed.value = "0.25";
    label.appendChild(speed);
    playButton.after(label);
    input.addEventListener("input", () => this.scrub(Number(input.value)));
    const TICK_MS = 40;
    playButton.addEventListener("click", () => {
      if (this.playing) { clearInterval(this.playing); this.playing = null; playButton.textContent = "Play"; return; }
      if (!this.data) return;
      playButton.textContent = "Pause";
      if (Number(input.value) >= Number(input.max)) input.value = 0;
      const t = this.data.t_s;
      // recorded time follows the wall clock (performance.now) at the chosen speed, not a count of
      // ticks: a tick that comes late (a busy page) moves the cursor further, so 1x plays in real time
      const start = t[Number(input.value)] || t[0];
      const wallStart = performance.now();
      let shownSpeed = Number(speed.value);
      let base = start, baseWall = wallStart;
      this.playing = setInterval(() => {
        const wall = performance.now();
        if (Number(speed.value) !== shownSpeed) { // a new speed applies from now on
          base += ((wall - baseWall) / 1000) * shownSpeed; baseWall = wall; shownSpeed = Number(speed.value);
        }
        const now = base + ((wall - baseWall) / 1000) * shownSpeed;
        let i = Number(input.value);
        while (i < t.length - 1 && t[i + 1] <= now) i += 1;
        if (i >= Number(input.max)) { input.value = input.max; this.scrub(Number(input.max)); clearInterval(this.playing); this.playing = null; playButton.textContent = "Play"; return; }
        input.value = i; this.scrub(i);
      }, TICK_MS);
    });
  }

  enableScrubber() {
    if (!this.scrubber || !this.data) return;
    this.scrubber.max = String(this.data.t_s.length - 1);
    this.scrubber.value = "0";
    this.scrubber.disabled = false;
    this.scrub(0);
  }

  /** Put every time chart's cursor at sample ``i`` and describe it in words. */
  scrub(i) {
    const tr = this.data;
    if (!tr || !tr.t_s.length) return;
    const t = tr.t_s[i];
    for (const key of ["qd", "u", "passive"]) {
      const c = this.charts[key];
      c.setCursor({ left: c.valToPos(t, "x"), top: 10 });
    }
    if (this.onScrub) this.onScrub(t, i);
    const qd = tr.qd[i] || [], u = tr.valve_u[i] || [];
    const phase = (tr.events || []).filter((e) => e.t_s <= t).map((e) => e.phase).pop() || "start";
    if (this.readout) {
      this.readout.textContent = `t = ${fmt(t)} s (${phase}) · ` + JOINTS.map((j, k) => `${j} ${fmt(qd[k])}`).join(", ") +
        (u.length ? ` · valves ${u.map((x) => fmt(x)).join(" ")}` : "");
    }
  }

  resize() {
    this.lastWidth = this.width();
    for (const c of Object.values(this.charts)) c.setSize({ width: this.lastWidth, height: 150 });
  }

  /** No charts (a throw without telemetry). */
  clear() {
    for (const c of Object.values(this.charts)) c.destroy();
    this.root.innerHTML = "";
    this.charts = {};
    this.data = null;
  }
}
