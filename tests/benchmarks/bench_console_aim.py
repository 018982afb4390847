"""How fast the console aims and repeats, measured in the page (Chromium, software WebGL) beside
a running simulated machine (`slinger up`, one machine, the deployed 2D and 3D policies with the
release check on):

* 2D preview: Preview pressed -> the nominal rollout shown (its row in the preview table), and
  -> the 1 sigma ellipse shown (the "1σ" row names its rollouts);
* 3D preview: the same, the ellipse is the figure;
* Throw -> next Throw: Throw pressed -> Throw enabled again (the throw was accepted and ran, the
  machine was reloaded, the page previewed again by itself and the server's gate judged that
  preview valid); a throw the server did not accept is a failed sample.

Run: ``PYTHONPATH=. python tests/benchmarks/bench_console_aim.py --repeats 5 [--breakdown] [--ab] [--out R.json]``
(not niced: it times the stack against whatever else the host runs, and says that load).
Prints p50/p95/max in seconds for each, with the host's load average and core count beside them
(each sample's load too), and the CPU seconds the job worker and its preview pool spent per
Preview click (nominal + ellipse: what a preview costs whatever else runs); ``--out`` writes them as a report (every sample with its load, the
figures with their bars, date, commit, policy SHA-256, host, command). ``--breakdown`` prints
and reports where each preview's time went (page, route, queue pick-up, worker, the twin's nominal
and Monte Carlo, the answer); ``--ab`` takes every other sample with the page's ellipse request apart
from its nominal (without ``extends``), so both are measured on one stack at one load.
Goals (issue of the console): 2D nominal <= 0.5 s, 2D ellipse <= 2 s, 3D ellipse <= 5 s (p95),
Throw -> next Throw <= 8 s.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.benchmarks.bench_console_estop import SOFTWARE_GL, host_load  # noqa: E402
from tests.browser import CHROMIUM, CHROMIUM_ARGS, log_in  # noqa: E402
from tests.conftest import SlingerUp  # noqa: E402

TIMED_PREVIEW = """() => new Promise((resolve) => {
    performance.clearResourceTimings();  // the buffer holds 250 entries; the page's checks fill it
    const t0 = performance.now(); let nominal = null;
    window.aimMarks = { t0: performance.timeOrigin + t0 };
    setTimeout(() => { obs.disconnect(); resolve([nominal === null ? null : nominal / 1000, null]); }, 300000);
    const seen = () => {
        const p = state.preview;
        if (nominal === null && p && p.status === 'ok' && document.getElementById('pv-down').textContent) {
            nominal = performance.now() - t0; aimMarks.nominal = performance.timeOrigin + t0 + nominal; aimMarks.nominalId = p.id; }
        if (/rollouts/.test(document.getElementById('pv-sigma').textContent) && nominal !== null) {
            aimMarks.ellipse = performance.now() + performance.timeOrigin; aimMarks.ellipseId = p.id;
            obs.disconnect(); resolve([nominal / 1000, (performance.now() - t0) / 1000]); }
        if (/No preview|failed/.test(document.getElementById('status').textContent)) { obs.disconnect(); resolve([null, null]); }
    };
    const obs = new MutationObserver(seen);
    obs.observe(document.body, { subtree: true, childList: true, characterData: true });
    document.getElementById('preview').click();
})"""

TIMED_REPEAT = """() => new Promise((resolve) => {
    const t0 = performance.now(); const btn = document.getElementById('throw'); let left = false, sent = false;
    const seen = () => {
        if (btn.disabled) left = true;
        if (state.throwId) sent = true;  // the server accepted the throw (its result clears it)
        const status = document.getElementById('status').textContent;
        // not sent, or the preview after it failed (a throw that failed leaves the gripper swinging):
        // Throw does not enable again by itself, a failed sample
        if (/throw was not sent/.test(status) || (sent && /Preview failed|No preview/.test(status))) { clearInterval(iv); resolve(null); }
        if (left && sent && !btn.disabled) { clearInterval(iv); resolve((performance.now() - t0) / 1000); }
    };
    const iv = setInterval(seen, 20);
    setTimeout(() => { clearInterval(iv); resolve(null); }, 300000);
    btn.click();
})"""


BREAKDOWN = r"""async () => {
    const m = window.aimMarks, o = performance.timeOrigin;
    const posts = performance.getEntriesByType('resource')
        .filter((e) => /\/api\/previews$/.test(e.name) && o + e.startTime >= m.t0 - 1)
        .sort((a, b) => a.startTime - b.startTime).slice(0, 2);
    const job = async (id) => { const r = await fetch(`/api/jobs/${id}`); return r.ok ? r.json() : null; };
    const [jn, je] = [await job(m.nominalId), await job(m.ellipseId)];
    return { marks: m, posts: posts.map((e) => [o + e.startTime, o + e.responseEnd]),
             jobs: [jn, je].map((j) => j && [j.created_at, j.started_at, j.finished_at, (j.result || {}).timing_s]) };
}"""
"""Where one timed preview's time went (wall-clock ms since the epoch, the page's and the
server's; one host): the page's marks, its two POST /api/previews (start, response end) and the
two jobs' rows (created, started, finished, the twin's own timing)."""


def breakdown(b: dict) -> dict[str, float]:
    """Phases of one timed preview, s: click -> nominal request sent, request -> job row
    created (the route's checks and submit), -> a worker started it (queue pick-up), -> finished
    (of which the twin's nominal / Monte Carlo, timing_s), -> response received (watcher, read
    back, HTTP), -> shown; the same for the ellipse, whose request follows the nominal's answer."""
    from datetime import datetime

    def ms(iso: str) -> float:
        return datetime.fromisoformat(iso).timestamp() * 1000.0

    m, out = b["marks"], {}
    if len(b["posts"]) < 2 or not all(b["jobs"]):
        return out
    shown = (m["nominal"], m["ellipse"])
    prev = m["t0"]
    for tag, (start, end), (created, started, finished, timing), at in zip(("n", "e"), b["posts"], b["jobs"], shown):
        out[f"{tag}.to_request"] = start - prev
        out[f"{tag}.submit"] = ms(created) - start
        out[f"{tag}.queue"] = ms(started) - ms(created)
        out[f"{tag}.job"] = ms(finished) - ms(started)
        out[f"{tag}.twin_nominal"] = 1000 * (timing or {}).get("nominal", float("nan"))
        out[f"{tag}.twin_mc"] = 1000 * (timing or {}).get("mc", float("nan"))
        out[f"{tag}.answer"] = end - ms(finished)
        out[f"{tag}.show"] = at - end
        prev = at
    return {k: round(v / 1000.0, 3) for k, v in out.items()}


BREAKDOWNS: list[dict] = []
"""Per timed preview with --breakdown: mode, target distance, phases (s, :func:`breakdown`), 1-min load."""


def timed_preview(page, mode: str, d: float, with_breakdown: bool,
                  variant: str = "as shipped") -> tuple[float | None, float | None]:
    """Time one Preview click (TIMED_PREVIEW); with ``with_breakdown`` print and keep where its time went."""
    n, e = page.evaluate(TIMED_PREVIEW)
    if with_breakdown and e is not None:
        phases = breakdown(page.evaluate(BREAKDOWN))
        BREAKDOWNS.append({"mode": mode, "distance_m": d, "variant": variant, "phases_s": phases,
                           "load_1min": round(os.getloadavg()[0], 1)})
        print("    " + " ".join(f"{k}={v:.3f}" for k, v in phases.items()), flush=True)
    return n, e


BARS = {"2D nominal preview": 0.5, "2D ellipse preview": 2.0, "3D ellipse preview": 5.0, "Throw -> next Throw enabled": 8.0}
"""Goals of the console's issue, s (p95)."""


def stats(values: list[float]) -> str:
    a = np.asarray([v for v in values if v is not None])
    if a.size == 0:
        return "no sample"
    return f"n={a.size} p50={np.percentile(a, 50):.2f} p95={np.percentile(a, 95):.2f} max={a.max():.2f} s"


def figure(what: str, values: list[float | None]) -> dict:
    """A report figure: n, p50/p95/max (s) of ``values`` (None: a sample that failed), the bar
    and whether p95 meets it, the host's load average now."""
    a = np.asarray([v for v in values if v is not None])
    out: dict = {"what": what, "unit": "s", "n": int(a.size), "failed": sum(v is None for v in values),
                 "load_1min_at_end": round(os.getloadavg()[0], 1)}
    if a.size:
        out.update(p50=round(float(np.percentile(a, 50)), 2), p95=round(float(np.percentile(a, 95)), 2),
                   max=round(float(a.max()), 2))
    if what in BARS:
        out.update(bar=f"<= {BARS[what]:g} s (p95)", met=bool(a.size) and out["p95"] <= BARS[what])
    return out


def _procs() -> dict[int, tuple[int, str, float]]:
    """pid -> (parent pid, command line, CPU seconds used so far) of every process (Linux /proc)."""
    out, tick = {}, os.sysconf("SC_CLK_TCK")
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        f = stat[stat.rindex(")") + 2:].split()
        out[int(d.name)] = (int(f[1]), cmd, (int(f[11]) + int(f[12])) / tick)
    return out


def worker_cpu_s(up_pid: int) -> float:
    """CPU seconds used so far by the stack's job worker and its descendants (the preview pool):
    what a preview costs, whatever else the host runs (the wall times depend on the load)."""
    procs = _procs()
    roots = [p for p, (pp, cmd, _) in procs.items() if pp == up_pid and "server.cli worker" in cmd]
    total, todo = 0.0, list(roots)
    while todo:
        pid = todo.pop()
        total += procs[pid][2]
        todo += [p for p, (pp, _, _) in procs.items() if pp == pid]
    return total


SAMPLES: list[dict] = []
"""Every sample of the run: what, target distance, seconds (None: failed), 1-min load average."""


def note(what: str, d: float, value: float | None, variant: str = "as shipped") -> None:
    SAMPLES.append({"what": what, "distance_m": d, "s": None if value is None else round(value, 3),
                    "load_1min": round(os.getloadavg()[0], 1), "variant": variant})


APART = """() => {
    // --ab: the page's ellipse request without extends (set window.benchApart)
    const original = window.fetch;
    window.fetch = (url, opts) => {
        if (window.benchApart && opts && opts.body && /\\/api\\/previews$/.test(String(url))) {
            const b = JSON.parse(opts.body); delete b.extends;
            opts = { ...opts, body: JSON.stringify(b) };
        }
        return original(url, opts);
    };
}"""
"""With --ab, every other sample sends the page's ellipse request without ``extends`` ("apart":
the ellipse starts from the machine state the server reads then, and the worker reuses the
nominal only if that state is bit for bit the nominal's), on the same stack at the same load."""


def set_target(page, x: float, y: float) -> None:
    page.fill("#target-x", str(x))
    page.fill("#target-y", str(y))
    page.locator("#target-set").dispatch_event("click")
    page.wait_for_function("() => !state.typed && !state.editing && state.target")
    page.locator("#preview:not([disabled])").wait_for()


def run(repeats: int, with_breakdown: bool = False, ab: bool = False) -> list[dict]:
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory(prefix="bench-console-aim-") as tmp, \
            SlingerUp(Path(tmp), machines=1, real_policies=True) as up, sync_playwright() as p:
        up.wait_machine_online("m1")
        browser = p.chromium.launch(executable_path=CHROMIUM, args=[a for a in CHROMIUM_ARGS if a != "--disable-gpu"]
                                    + SOFTWARE_GL, timeout=60_000)
        try:
            page = browser.new_context(viewport={"width": 1440, "height": 900}).new_page()
            page.set_default_timeout(300_000)
            if ab:
                page.add_init_script(f"({APART})()")
            log_in(page, up.base_url)
            page.locator("#machine-state", has_text="m1 READY").wait_for()
            targets = [7.0 + 0.6 * (i % 5) for i in range(repeats)]
            nominal, ellipse, repeat, cpu = [], [], [], []
            apart: dict[str, list] = {}
            variants = ["apart" if ab and i % 2 else "as shipped" for i in range(repeats)]
            for i, d in enumerate(targets):
                page.locator("#machine-state", has_text="m1 READY").wait_for()
                set_target(page, d, 0.0)
                page.evaluate("(v) => { window.benchApart = v; }", variants[i] == "apart")
                c0 = worker_cpu_s(up.proc.pid)
                n, e = timed_preview(page, "2d", d, with_breakdown, variants[i])
                c = worker_cpu_s(up.proc.pid) - c0
                r = None
                if e is not None:  # a preview that failed (the page says why) is not thrown
                    page.locator("#throw:not([disabled])").wait_for()
                    r = page.evaluate(TIMED_REPEAT)
                got = (("2D nominal preview", n), ("2D ellipse preview", e), ("Throw -> next Throw enabled", r),
                       ("2D worker CPU per Preview (nominal + ellipse)", c))
                if variants[i] == "apart":
                    for what, v in got:
                        apart.setdefault(what, []).append(v)
                else:
                    for lst, v in zip((nominal, ellipse, repeat, cpu), (n, e, r, c)):
                        lst.append(v)
                for what, v in got:
                    note(what, d, v, variants[i])
                print(f"  2D {d:.1f} m ({variants[i]}): nominal {n} s, ellipse {e} s, Throw -> Throw {r} s, worker CPU "
                      f"{c:.2f} s per Preview ({host_load()})", flush=True)
            print(f"2D nominal preview: {stats(nominal)}  ({host_load()})", flush=True)
            print(f"2D ellipse preview: {stats(ellipse)}  ({host_load()})", flush=True)
            print(f"Throw -> next Throw enabled: {stats(repeat)}  ({host_load()})", flush=True)
            page.check("input[name=mode][value='3d']")
            page.wait_for_function("() => state.mode === '3d'")
            nominal3, ellipse3, cpu3 = [], [], []
            for i, d in enumerate(targets):
                page.locator("#machine-state", has_text="m1 READY").wait_for()
                set_target(page, d, 1.0)
                page.evaluate("(v) => { window.benchApart = v; }", variants[i] == "apart")
                c0 = worker_cpu_s(up.proc.pid)
                n, e = timed_preview(page, "3d", d, with_breakdown, variants[i])
                c = worker_cpu_s(up.proc.pid) - c0
                got = (("3D nominal preview", n), ("3D ellipse preview", e), ("3D worker CPU per Preview (nominal + ellipse)", c))
                if variants[i] == "apart":
                    for what, v in got:
                        apart.setdefault(what, []).append(v)
                else:
                    for lst, v in zip((nominal3, ellipse3, cpu3), (n, e, c)):
                        lst.append(v)
                for what, v in got:
                    note(what, d, v, variants[i])
                print(f"  3D {d:.1f} m ({variants[i]}): nominal {n} s, ellipse {e} s, worker CPU {c:.2f} s per Preview "
                      f"({host_load()})", flush=True)
            print(f"3D nominal preview: {stats(nominal3)}  ({host_load()})", flush=True)
            print(f"3D ellipse preview: {stats(ellipse3)}  ({host_load()})", flush=True)
            print(f"worker CPU per Preview (nominal + ellipse): 2D {stats(cpu)}, 3D {stats(cpu3)}", flush=True)
            for what, v in apart.items():
                print(f"{what}, apart (A/B): {stats(v)}", flush=True)
            return [figure("2D nominal preview", nominal), figure("2D ellipse preview", ellipse),
                    figure("Throw -> next Throw enabled", repeat), figure("3D nominal preview", nominal3),
                    figure("3D ellipse preview", ellipse3),
                    {**figure("2D worker CPU per Preview (nominal + ellipse)", cpu), "unit": "s CPU"},
                    {**figure("3D worker CPU per Preview (nominal + ellipse)", cpu3), "unit": "s CPU"}] + [
                {**figure(what, v), "what": f"{what}, apart (A/B)", **({"unit": "s CPU"} if "CPU" in what else {})}
                for what, v in apart.items()]
        finally:
            browser.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=5, help="previews (and throws) per mode")
    ap.add_argument("--out", type=Path, default=None, help="write the report (JSON) here")
    ap.add_argument("--breakdown", action="store_true",
                    help="print (and report) where each preview's time went: page, route, queue, worker, answer")
    ap.add_argument("--ab", action="store_true",
                    help="every other sample with the page's ellipse request apart from its nominal (no extends)")
    ap.add_argument("--host-note", default="", help="what else ran on the host, for the report")
    a = ap.parse_args()
    start = host_load()
    print(f"{start} at the start", flush=True)
    figures = run(a.repeats, a.breakdown, a.ab)
    end = host_load()
    print(f"{end} at the end")
    if a.out:
        from server.site.results_page import host_description

        from sim_twin.provenance import short_commit

        commit = short_commit() or "unknown"
        policies = [{"name": json.loads((REPO / "policies" / f"throw{m}.json").read_text()).get("name", f"throw{m}"),
                     "deployed_as": f"policies/throw{m}.onnx",
                     "sha256": hashlib.sha256((REPO / "policies" / f"throw{m}.onnx").read_bytes()).hexdigest()}
                    for m in ("2d", "3d")]
        report = {"provenance": {
            "title": "Console aiming: preview and Throw -> next Throw in the page, beside a running simulated machine",
            "date": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"), "commit": commit or "not recorded",
            "policies": policies, "host": f"{host_description()}; {start} at the start, {end} at the end"
                                          + (f"; {a.host_note}" if a.host_note else ""),
            "command": f"PYTHONPATH=. python tests/benchmarks/bench_console_aim.py --repeats {a.repeats}"
                       + (" --breakdown" if a.breakdown else "") + (" --ab" if a.ab else "") + f" --out {a.out}", "recorded": "at run time by the benchmark",
            "note": "Chromium (software WebGL) on the console page of a `slinger up --machines 1` stack (the deployed "
                    "policies, the release check on) started by the benchmark; everything on the SIMULATED machine"},
            "measures": figures, "samples": SAMPLES, **({"breakdowns": BREAKDOWNS} if a.breakdown else {})}
        a.out.write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
