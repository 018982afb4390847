"""Report of a `slinger train` run's site-matrix gate: wall time to each bar.

``python -m tests.benchmarks.training_run_report policies/training/<run> [<run> ...] --out reports/<name>``
reads ``<run>/matrices/matrix_gate.json`` and the matrices beside it and writes ``<name>.md``,
``<name>.json`` and ``<name>.png`` (cells missing a bar against training wall time). For every
profile it gives the first checkpoint (training wall time) at which that profile met all its bars
on the gate's first seed, and whether it kept meeting them after. With several runs (one recipe's
training seeds, say) it writes one report: a table of each run's wall time to the bars, then a
section per run, and one line per run in the plot; ``--command``, given once, may name each run's
``{name}`` and training ``{seed}``, or is given once per run; each ``--after-run`` matrix belongs to
the run whose directory holds it.

For 2D runs each row also gives the far-target bias (:func:`far_bias`: the mean landing minus the
target at the matrix's farthest target, nominal and sensor-latency profiles), and the run's mean of it
over the first gate seed's matrices from iteration ``FAR_BIAS_FROM`` on (after the curriculum stage of
the candidate recipes) with its sample standard deviation over those matrices (how far it moves from
checkpoint to checkpoint): the overshoot that stalls runs of those recipes (docs/training.md, "Four
more seeds, and the far-target overshoot").

The report also summarises the run's ``curve.csv`` at up to ``CURVE_ROWS`` checkpoints (evenly
spaced, the last included): landings, failures and time-outs per finished episode, mean impact
error, return, episode length, action std and control steps per second with learning.

``--after-run <run>/matrices/site_matrix_<mode>_it<N>[_seed<S>].json ...`` adds site matrices of
later checkpoints run after the training stopped (``slinger evaluate --policy ... --matrix --seed
S``, another host): their rows are marked "after the run", their training wall time is the one
``curve.csv`` gives for iteration N. They count for no verdict of the gate (its ``passed``), but a
run's wall time to the bars is that of the first iteration met on every gate seed by either
(:func:`first_pass`), marked where a seed was judged after the run.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import platform
import statistics
import textwrap
from datetime import UTC, datetime
from pathlib import Path

CURVE_ROWS = 14
CELL_TICKS = (0, 1, 2, 3, 4, 6, 10, 20, 40, 66)  # labelled counts of cells missing a bar
FAR_BIAS_PROFILES = ("nominal", "sensor_latency")
"""The profiles whose far-target bias the report gives: the two whose 9.5-10 m accuracy the stalled
candidate runs missed by an overshoot (throw2d-scratch-f0, -g0)."""
FAR_BIAS_FROM = 400
"""First iteration of a run's mean far-target bias: after the candidate recipes' curriculum stage at
iteration 300 and the matrices just after it, which it unsettles (throw2d-scratch-g0: 49 cells short
at iteration 325)."""


def far_bias(rep: dict) -> dict[str, float]:
    """Bias [m] (mean landing minus target, downrange, + long) at the farthest target of each of
    ``FAR_BIAS_PROFILES`` in one site matrix (sim_twin.evaluation.matrix's JSON); {} for a 3D matrix
    or one without those profiles."""
    if rep.get("mode") != "2d":
        return {}
    out = {}
    for prof in rep["profiles"]:
        if prof["name"] in FAR_BIAS_PROFILES and prof["targets"]:
            far = max(prof["targets"], key=lambda t: t["target_m"])
            out[prof["name"]] = round(far["bias_m"], 3)
    return out


def exported_policy_sha256(run: Path) -> str | None:
    """The ONNX SHA-256 of the policy ``run`` exported (from its model card ``throw<mode>.card.json``,
    written when a checkpoint met every bar), or None when the run exported none.

    Raises:
        KeyError: a model card without ``onnx_sha256``.
    """
    cards = sorted(run.glob("throw*.card.json"))
    return json.loads(cards[0].read_text())["onnx_sha256"] if cards else None


THROUGHPUT_FROM = 50
"""First iteration of a run's median throughput: the first chunks include JAX's compilation."""


def median_throughput(run: Path) -> float | None:
    """Median control steps/s with learning (all processes, as ``curve.csv`` records each chunk) over
    the checkpoints from iteration :data:`THROUGHPUT_FROM` on; None without such rows. On a machine
    shared by several runs and their gates (tests/benchmarks/device_runs.sh) it is that run's share."""
    from sim_twin.training.curve import TrainingCurve

    rates = [r["control_steps_per_s"] for r in TrainingCurve.load_or_new(run / "curve.csv").rows
             if r["iteration"] >= THROUGHPUT_FROM and math.isfinite(r.get("control_steps_per_s", math.nan))]
    return statistics.median(rates) if rates else None


def curve_summary(run: Path, rows: int = CURVE_ROWS) -> list[dict]:
    """Up to ``rows`` checkpoints of ``run/curve.csv``, evenly spaced with the last included, each
    {iteration, wall_min, landed_per_done, failed_per_done, timeouts_per_done (the rest of the
    finished episodes: time limit reached without a landing or failure), impact_err_m [m],
    mean_reward, mean_episode_length [control steps], action_std, control_steps_per_s (with
    learning, all processes)}; [] without a curve."""
    from sim_twin.training.curve import TrainingCurve

    curve = TrainingCurve.load_or_new(run / "curve.csv").rows
    if not curve:
        return []
    n = min(rows, len(curve))
    picks = sorted({round(k * (len(curve) - 1) / max(n - 1, 1)) for k in range(n)})
    out = []
    for r in (curve[i] for i in picks):
        landed, failed = r.get("landed_per_done", float("nan")), r.get("failed_per_done", float("nan"))
        out.append({"iteration": int(r["iteration"]), "wall_min": round(r["wall_s"] / 60, 1),
                    "landed_per_done": landed, "failed_per_done": failed, "timeouts_per_done": 1.0 - landed - failed,
                    **{k: r.get(k, float("nan")) for k in ("impact_err_m", "mean_reward", "mean_episode_length", "action_std",
                                                                "control_steps_per_s")}})
    return out


def curve_table(summary: list[dict]) -> list[str]:
    """Markdown lines of :func:`curve_summary`'s rows."""
    md = ["| iteration | training wall time [min] | landed | failed | timed out | mean impact error [m] | mean return | "
          "mean episode length | action std | M control steps/s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for c in summary:
        md.append(f"| {c['iteration']} | {c['wall_min']} | {c['landed_per_done']:.1%} | {c['failed_per_done']:.2%} | "
                  f"{c['timeouts_per_done']:.2%} | {c['impact_err_m']:.3f} | {c['mean_reward']:.1f} | "
                  f"{c['mean_episode_length']:.0f} | {c['action_std']:.3f} | {c['control_steps_per_s'] / 1e6:.2f} |")
    return md


def run_report(run: Path, gpu: str, command: str, after_run: list[Path], gate_unrecorded: list[Path]) -> tuple[dict, list[str]]:
    """One run's report: the JSON dict (without date, commit and host) and its Markdown section.

    Raises:
        FileNotFoundError: ``run`` has no ``matrices/matrix_gate.json``.
        ValueError: a bad ``after_run`` / ``gate_unrecorded`` matrix (:func:`after_run_row`).
    """
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    wall = train_wall_s(run) if after_run or gate_unrecorded else {}
    rows = ([dict(r, after_run=False, note=None) for r in gate["results"]]
            + [after_run_row(run, m, wall) for m in after_run]
            + [after_run_row(run, m, wall, note=UNRECORDED) for m in gate_unrecorded])
    rows.sort(key=lambda r: (r["iteration"], r["seed"]))
    first_seed = gate["seeds"][0]
    per_profile: dict[str, list[tuple[float, int, bool]]] = {}
    for r in rows:
        rep = json.loads(Path(run / "matrices" / Path(r["matrix_path"]).name).read_text())
        r["far_bias_m"] = far_bias(rep)
        if r["seed"] != first_seed:
            continue
        for prof in rep["profiles"]:
            per_profile.setdefault(prof["name"], []).append((r["train_wall_s"], r["iteration"], prof["pass"]))
    first_met = {}
    for name, hist in per_profile.items():
        met = [(t, it) for t, it, ok in hist if ok]
        kept = bool(met) and all(ok for t, it, ok in hist if t >= met[0][0])
        first_met[name] = {"wall_min": round(met[0][0] / 60, 1) if met else None, "iteration": met[0][1] if met else None, "kept": kept}
    late = [r["far_bias_m"] for r in rows if r["seed"] == first_seed and r["iteration"] >= FAR_BIAS_FROM and r["far_bias_m"]]
    mean_far_bias = {name: round(sum(b[name] for b in late) / len(late), 3) for name in FAR_BIAS_PROFILES
                     if late and all(name in b for b in late)}
    sd_far_bias = {name: round(statistics.stdev(b[name] for b in late), 3) for name in mean_far_bias} if len(late) > 1 else {}
    ckpt = run / "checkpoint.pt"
    policy_sha256 = exported_policy_sha256(run)
    passed = gate["passed"]
    first = first_pass(rows, gate["seeds"])
    out = {
        "gpu": gpu,
        "command": command,
        "run": str(run),
        "checkpoint_sha256": hashlib.sha256(ckpt.read_bytes()).hexdigest() if ckpt.exists() else None,
        "policy_sha256": policy_sha256,
        "seeds": gate["seeds"],
        "passed": passed,
        "first_pass": first,
        "bars_wall_min": round(first["train_wall_s"] / 60, 1) if first else None,
        "results": [{k: r[k] for k in ("iteration", "seed", "passed", "missing_cells", "train_wall_s", "misses", "after_run", "note",
                                       "far_bias_m")}
                    for r in rows],
        "mean_far_bias_m": mean_far_bias,
        "sd_far_bias_m": sd_far_bias,
        "mean_far_bias_from_iteration": FAR_BIAS_FROM,
        "first_met_per_profile": first_met,
        "curve": curve_summary(run),
        "median_control_steps_per_s": median_throughput(run),
        "median_control_steps_per_s_from_iteration": THROUGHPUT_FROM,
    }
    verdict = f"yes, {first_pass_text(first)} ({out['bars_wall_min']} min)" if first else "no"
    md = [(f"checkpoint SHA-256 `{out['checkpoint_sha256']}`; " if out["checkpoint_sha256"] else "checkpoint not kept; ")
          + (f"exported policy ONNX SHA-256 `{policy_sha256}`; " if policy_sha256 else "")
          + f"command `{command}`. Gate seeds {gate['seeds']}; every bar met on every seed: "
          f"**{verdict}**.", "",
          "| iteration | training wall time [min] | seed | cells missing a bar (of 66) | far-target bias, "
          + " / ".join(FAR_BIAS_PROFILES) + " [m] | misses |", "|---|---|---|---|---|---|"]
    for r in rows:
        miss = "; ".join(r["misses"]) if r["missing_cells"] <= 6 else f"{r['missing_cells']} cells"
        it = f"{r['iteration']} ({r['note']})" if r["note"] else str(r["iteration"])
        bias = " / ".join(f"{r['far_bias_m'][n]:+.3f}" for n in FAR_BIAS_PROFILES) if len(r["far_bias_m"]) == len(FAR_BIAS_PROFILES) else "-"
        md.append(f"| {it} | {r['train_wall_s'] / 60:.1f} | {r['seed']} | {r['missing_cells']} | {bias} | {miss} |")
    if mean_far_bias:
        md += ["", f"Mean far-target bias over the seed-{first_seed} matrices from iteration {FAR_BIAS_FROM} on ({len(late)}): "
               + ", ".join(f"{n} {b:+.3f} m" + (f" (standard deviation {sd_far_bias[n]:.3f} m)" if n in sd_far_bias else "")
                           for n, b in mean_far_bias.items()) + "."]
    md += ["", f"First checkpoint at which each profile met all its bars (seed {first_seed}):", "",
           "| profile | training wall time [min] | iteration | met at every later checkpoint |", "|---|---|---|---|"]
    for name, f in first_met.items():
        md.append(f"| {name} | {f['wall_min'] if f['wall_min'] is not None else 'not met'} | {f['iteration'] or '-'} | {'yes' if f['kept'] else 'no'} |")
    if out["curve"]:
        md += ["", "Training curve (`curve.csv`; per finished episode: landed, failed, or timed out without either):", "",
               *curve_table(out["curve"])]
    return out, md


def first_pass(rows: list[dict], gate_seeds: list[int]) -> dict | None:
    """The first iteration whose matrices met every bar on every gate seed, the gate's own verdicts
    (recorded or not) and after-run matrices of those seeds alike: {iteration, train_wall_s [s], after_run_seeds (the gate
    seeds judged after the run, [] when the gate judged them all)}; None when no iteration did. A
    seed outside ``gate_seeds`` (a held-out one) does not count. The gate's ``passed`` can be later:
    a machine that went back while the gate ran a candidate's second seed leaves that verdict to an
    after-run matrix (throw2d-scratch-g1, iteration 575)."""
    by_it: dict[int, dict[int, dict]] = {}
    for r in rows:
        if r["seed"] in gate_seeds:
            by_it.setdefault(r["iteration"], {})[r["seed"]] = r
    for it in sorted(by_it):
        seeds = by_it[it]
        if set(seeds) == set(gate_seeds) and all(r["passed"] for r in seeds.values()):
            return {"iteration": it, "train_wall_s": seeds[gate_seeds[0]]["train_wall_s"],
                    "after_run_seeds": sorted(s for s, r in seeds.items() if r["after_run"])}
    return None


def first_pass_text(first: dict) -> str:
    """"iteration N", with the seeds judged after the run where there are."""
    after = first["after_run_seeds"]
    return f"iteration {first['iteration']}" + (f" (seed {', '.join(map(str, after))} after the run)" if after else "")


def far_style(run: Path) -> dict | None:
    """A 2D run's far-target throw style by iteration 250, read from its gate's seed-0 matrices
    (tests/benchmarks/training_throw_style.py's run_style: {style, far_duration_s [s],
    style_iteration, ...}), or None for a run without 2D gate matrices."""
    from tests.benchmarks.training_throw_style import RunSource, run_style

    if not list((run / "matrices").glob("site_matrix_2d_it*.json")):
        return None
    return run_style(RunSource(str(run)))


def training_seed(run: Path) -> int | None:
    """The run's training seed: its ``config.json``'s ``training.seed`` or, for a run from before the
    config recorded it, the ``--seed`` of its model card's command; None when neither says."""
    if (run / "config.json").exists():
        seed = json.loads((run / "config.json").read_text()).get("training", {}).get("seed")
        if seed is not None:
            return int(seed)
    for card in sorted(run.glob("throw*.card.json")):
        words = json.loads(card.read_text()).get("command", "").split()
        if "--seed" in words[:-1]:
            return int(words[words.index("--seed") + 1])
    return None


def run_command(template: str, run: Path) -> str:
    """``template`` with ``{name}`` (the run directory's name) and ``{seed}`` (:func:`training_seed`) filled in."""
    return template.replace("{name}", run.name).replace("{seed}", str(training_seed(run)))


def main() -> None:
    from sim_twin.provenance import head_commit

    p = argparse.ArgumentParser()
    p.add_argument("runs", type=Path, nargs="+", help="run directories; several: one report with a section per run")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--gpu", default="one NVIDIA H100 80GB HBM3")
    p.add_argument("--command", action="append", default=None,
                   help="how the run was made (default `slinger train --mode 2d`): once for every run, where {name} and "
                        "{seed} are each run's directory name and training seed, or once per run in the runs' order")
    p.add_argument("--title", default=None, help="the report's title with several runs")
    p.add_argument("--after-run", type=Path, nargs="*", default=[],
                   help="site matrices of later checkpoints run after the training (site_matrix_<mode>_it<N>[_seed<S>].json)")
    p.add_argument("--gate-unrecorded", type=Path, nargs="*", default=[],
                   help="site matrices the gate ran during the training whose verdict matrix_gate.json lacks")
    a = p.parse_args()
    twice = sorted({str(r) for r in a.runs if sum(x.resolve() == r.resolve() for x in a.runs) > 1})
    if twice:
        p.error(f"run directories given more than once: {', '.join(twice)} (one section and one table row per run)")
    commands = a.command or ["slinger train --mode 2d"]
    if len(commands) not in (1, len(a.runs)):
        p.error(f"--command given {len(commands)} times for {len(a.runs)} runs: give it once or once per run")
    reports = []
    for k, run in enumerate(a.runs):
        mine = [m for m in a.after_run if m.resolve().is_relative_to(run.resolve())]
        unrec = [m for m in a.gate_unrecorded if m.resolve().is_relative_to(run.resolve())]
        reports.append(run_report(run, a.gpu, run_command(commands[k % len(commands)], run), mine, unrec))
    commit = (head_commit() or ("",))[0]
    head = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit, "host": platform.node()}
    curves = {Path(r["run"]).name: [(x["train_wall_s"] / 60, x["missing_cells"]) for x in r["results"] if x["seed"] == r["seeds"][0]]
              for r, _ in reports}
    a.out.parent.mkdir(parents=True, exist_ok=True)
    if len(reports) == 1:
        (out, md) = reports[0]
        a.out.with_suffix(".json").write_text(json.dumps({**head, **out}, indent=2) + "\n")
        lines = [f"# Training run {a.runs[0].name}: wall time to the site-matrix bars", "",
                 f"Date {head['date']}, commit `{commit}`, {a.gpu}; " + md[0], *md[1:]]
    else:
        lines = [f"# {a.title or 'Training runs'}: wall time to the site-matrix bars", "",
                 f"Date {head['date']}, commit `{commit}`, {a.gpu}.", "",
                 "| run | training seed | far-target style by iteration 250 | every bar on every gate seed | "
                 f"training wall time to the bars [min] | median control steps/s with learning from iteration {THROUGHPUT_FROM} [M] "
                 f"| mean far-target bias from iteration {FAR_BIAS_FROM} "
                 "(± its standard deviation over those matrices), " + " / ".join(FAR_BIAS_PROFILES)
                 + " [m] | last verdict on a gate seed | held-out seeds |",
                 "|---|---|---|---|---|---|---|---|---|"]
        for r, _ in reports:
            on_gate = [x for x in r["results"] if x["seed"] in r["seeds"]]
            last = on_gate[-1] if on_gate else None
            held_out = "; ".join(f"iteration {x['iteration']}, seed {x['seed']}: "
                                 + ("every bar" if x["passed"] else "; ".join(x["misses"]) if x["missing_cells"] <= 3
                                    else f"{x['missing_cells']} cells missing")
                                 for x in r["results"] if x["seed"] not in r["seeds"]) or "-"
            seed = training_seed(Path(r["run"]))
            rate = r["median_control_steps_per_s"]
            throughput = "-" if rate is None else f"{rate / 1e6:.2f}"
            style = r["far_style"] = far_style(Path(r["run"]))
            style_text = f"{style['style']} ({style['far_duration_s']} s, iteration {style['style_iteration']})" if style else "-"
            verdict = (f"iteration {last['iteration']}, seed {last['seed']}: {last['missing_cells']} cells missing"
                       + (" (after the run)" if last["after_run"] else "")) if last else "none"
            lines.append(f"| {Path(r['run']).name} | {seed} | {style_text} | "
                         f"{'yes, ' + first_pass_text(r['first_pass']) if r['first_pass'] else 'no'} | "
                         f"{r['bars_wall_min'] if r['bars_wall_min'] is not None else 'not met'} | "
                         f"{throughput} | "
                         + (" / ".join(f"{r['mean_far_bias_m'][n]:+.3f}" + (f" ± {r['sd_far_bias_m'][n]:.3f}" if n in r["sd_far_bias_m"] else "")
                                       for n in FAR_BIAS_PROFILES)
                            if len(r["mean_far_bias_m"]) == len(FAR_BIAS_PROFILES) else "-") + f" | {verdict} | {held_out} |")
        a.out.with_suffix(".json").write_text(json.dumps({**head, "gpu": a.gpu, "runs": [r for r, _ in reports]}, indent=2) + "\n")
        for (r, md) in reports:
            lines += ["", f"## {Path(r['run']).name}", "", md[0][0].upper() + md[0][1:], *md[1:]]
    a.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    plot_cells(curves, a.out.with_suffix(".png"), a.title or (a.runs[0].name if len(a.runs) == 1 else "training runs"))


def plot_cells(curves: dict[str, list[tuple[float, int]]], path: Path, title: str) -> None:
    """Cells missing a bar on the first gate seed against training wall time [min], one line per run."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    many = len(curves) > 6  # the legend goes beside the axes, where it hides no line
    columns = 2 if len(curves) > 12 else 1  # more than 12 rows of legend run off the figure's 3.8 in
    fig, ax = plt.subplots(figsize=(6.5 + 2.5 * columns if many else 6.5, 3.8))
    if len(curves) > 10:  # the default cycle has 10 colours: no two runs share one
        ax.set_prop_cycle(color=plt.get_cmap("tab20").colors)
    for name, pts in curves.items():
        ax.plot([t for t, _ in pts], [n for _, n in pts], "o-", label=name)
    ax.set_yscale("symlog", linthresh=1)
    # symlog labels only decades: runs whose counts stay within one (3-6 cells, say) got no labels
    top = max([n for pts in curves.values() for _, n in pts], default=1)
    ax.set_yticks([v for v in CELL_TICKS if v <= max(top, 1)])
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xlabel("training wall time [min]")
    ax.set_ylabel("site-matrix cells missing a bar")
    # a report's title can run to a paragraph (its provenance keeps it whole): two lines of it here
    ax.set_title(textwrap.fill(textwrap.shorten(title, 180, placeholder=" ..."), 90)
                 + "\ncells missing a bar (first gate seed, 66 cells)", fontsize=9)
    ax.grid(alpha=0.3)
    if len(curves) > 1:
        ax.legend(fontsize=8, ncol=columns,
                  **({"loc": "upper left", "bbox_to_anchor": (1.01, 1.0)} if many else {}))
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def train_wall_s(run: Path) -> dict[int, float]:
    """Training wall time [s] per iteration, from the run's curve.csv."""
    from sim_twin.training.curve import TrainingCurve

    return {int(r["iteration"]): r["wall_s"] for r in TrainingCurve.load_or_new(run / "curve.csv").rows}


AFTER_RUN = "after the run"
UNRECORDED = "the gate's matrix, its verdict not recorded"


def after_run_row(run: Path, matrix: Path, wall: dict[int, float], note: str = AFTER_RUN) -> dict:
    """A report row for a site matrix that ``matrix_gate.json`` does not hold: one run after the
    training (``note`` AFTER_RUN, the default) or one the gate ran whose verdict was not recorded
    (UNRECORDED). Iteration and seed come from the file's name, training wall time [s] from ``wall``
    (:func:`train_wall_s` of the run). Raises ValueError on a name that is not
    site_matrix_<mode>_it<N>[_seed<S>].json or an iteration the curve lacks."""
    from sim_twin.training.matrix_gate import parse_matrix_file_name, summarise_matrix

    try:
        iteration, seed = parse_matrix_file_name(matrix.name)
    except ValueError as e:
        raise ValueError(f"{matrix.parent}/{e}") from None
    if iteration not in wall:
        raise ValueError(f"{matrix}: iteration {iteration} is not in {run / 'curve.csv'}")
    rep = json.loads(matrix.read_text())
    n_miss, misses = summarise_matrix(rep)
    return {"iteration": iteration, "seed": seed, "passed": bool(rep["pass"]), "missing_cells": n_miss, "matrix_path": str(matrix),
            "train_wall_s": wall[iteration], "misses": misses, "after_run": note == AFTER_RUN, "note": note}


if __name__ == "__main__":
    main()
