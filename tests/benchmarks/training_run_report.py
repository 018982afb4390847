"""Report of a `slinger train` run's site-matrix gate: wall time to each bar.

``python tests/benchmarks/training_run_report.py policies/training/<run> --out reports/<name>``
reads ``<run>/matrices/matrix_gate.json`` and the matrices beside it and writes ``<name>.md``,
``<name>.json`` and ``<name>.png`` (cells missing a bar against training wall time). For every
profile it gives the first checkpoint (training wall time) at which that profile met all its bars
on the gate's first seed, and whether it kept meeting them after.

The report also summarises the run's ``curve.csv`` at up to ``CURVE_ROWS`` checkpoints (evenly
spaced, the last included): landings, failures and time-outs per finished episode, mean impact
error, return, episode length, action std and control steps per second with learning.

``--after-run <run>/matrices/site_matrix_<mode>_it<N>[_seed<S>].json ...`` adds site matrices of
later checkpoints run after the training stopped (``slinger evaluate --policy ... --matrix --seed
S``, another host): their rows are marked "after the run", their training wall time is the one
``curve.csv`` gives for iteration N, and they count for no verdict of the gate.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import subprocess
from datetime import UTC, datetime
from pathlib import Path

CURVE_ROWS = 14
CELL_TICKS = (0, 1, 2, 3, 4, 6, 10, 20, 40, 66)  # labelled counts of cells missing a bar


def exported_policy_sha256(run: Path) -> str | None:
    """The ONNX SHA-256 of the policy ``run`` exported (from its model card ``throw<mode>.card.json``,
    written when a checkpoint met every bar), or None when the run exported none.

    Raises:
        KeyError: a model card without ``onnx_sha256``.
    """
    cards = sorted(run.glob("throw*.card.json"))
    return json.loads(cards[0].read_text())["onnx_sha256"] if cards else None


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


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("run", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--gpu", default="one NVIDIA H100 80GB HBM3")
    p.add_argument("--command", default="slinger train --mode 2d")
    p.add_argument("--after-run", type=Path, nargs="*", default=[],
                   help="site matrices of later checkpoints run after the training (site_matrix_<mode>_it<N>[_seed<S>].json)")
    p.add_argument("--gate-unrecorded", type=Path, nargs="*", default=[],
                   help="site matrices the gate ran during the training whose verdict matrix_gate.json lacks")
    a = p.parse_args()
    gate = json.loads((a.run / "matrices" / "matrix_gate.json").read_text())
    wall = train_wall_s(a.run) if a.after_run or a.gate_unrecorded else {}
    rows = ([dict(r, after_run=False, note=None) for r in gate["results"]]
            + [after_run_row(a.run, m, wall) for m in a.after_run]
            + [after_run_row(a.run, m, wall, note=UNRECORDED) for m in a.gate_unrecorded])
    rows.sort(key=lambda r: (r["iteration"], r["seed"]))
    first_seed = gate["seeds"][0]
    per_profile: dict[str, list[tuple[float, int, bool]]] = {}
    for r in rows:
        if r["seed"] != first_seed:
            continue
        rep = json.loads(Path(a.run / "matrices" / Path(r["matrix_path"]).name).read_text())
        for prof in rep["profiles"]:
            per_profile.setdefault(prof["name"], []).append((r["train_wall_s"], r["iteration"], prof["pass"]))
    first_met = {}
    for name, hist in per_profile.items():
        met = [(t, it) for t, it, ok in hist if ok]
        kept = bool(met) and all(ok for t, it, ok in hist if t >= met[0][0])
        first_met[name] = {"wall_min": round(met[0][0] / 60, 1) if met else None, "iteration": met[0][1] if met else None, "kept": kept}
    ckpt = a.run / "checkpoint.pt"
    policy_sha256 = exported_policy_sha256(a.run)
    commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    out = {
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "commit": commit,
        "host": platform.node(),
        "gpu": a.gpu,
        "command": a.command,
        "run": str(a.run),
        "checkpoint_sha256": hashlib.sha256(ckpt.read_bytes()).hexdigest() if ckpt.exists() else None,
        "policy_sha256": policy_sha256,
        "seeds": gate["seeds"],
        "passed": gate["passed"],
        "results": [{k: r[k] for k in ("iteration", "seed", "passed", "missing_cells", "train_wall_s", "misses", "after_run", "note")}
                    for r in rows],
        "first_met_per_profile": first_met,
        "curve": curve_summary(a.run),
    }
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.with_suffix(".json").write_text(json.dumps(out, indent=2) + "\n")
    md = [f"# Training run {a.run.name}: wall time to the site-matrix bars", "",
          f"Date {out['date']}, commit `{commit}`, {a.gpu}; "
          + (f"checkpoint SHA-256 `{out['checkpoint_sha256']}`; " if out["checkpoint_sha256"] else "checkpoint not kept; ")
          + (f"exported policy ONNX SHA-256 `{policy_sha256}`; " if policy_sha256 else "")
          + f"command `{a.command}`. Gate seeds {gate['seeds']}; every bar met on every seed: "
          f"**{'yes, iteration ' + str(gate['passed']['iteration']) if gate['passed'] else 'no'}**.", "",
          "| iteration | training wall time [min] | seed | cells missing a bar (of 66) | misses |", "|---|---|---|---|---|"]
    for r in rows:
        miss = "; ".join(r["misses"]) if r["missing_cells"] <= 6 else f"{r['missing_cells']} cells"
        it = f"{r['iteration']} ({r['note']})" if r["note"] else str(r["iteration"])
        md.append(f"| {it} | {r['train_wall_s'] / 60:.1f} | {r['seed']} | {r['missing_cells']} | {miss} |")
    md += ["", f"First checkpoint at which each profile met all its bars (seed {first_seed}):", "",
           "| profile | training wall time [min] | iteration | met at every later checkpoint |", "|---|---|---|---|"]
    for name, f in first_met.items():
        md.append(f"| {name} | {f['wall_min'] if f['wall_min'] is not None else 'not met'} | {f['iteration'] or '-'} | {'yes' if f['kept'] else 'no'} |")
    if out["curve"]:
        md += ["", "Training curve (`curve.csv`; per finished episode: landed, failed, or timed out without either):", "",
               *curve_table(out["curve"])]
    a.out.with_suffix(".md").write_text("\n".join(md) + "\n")

    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    s0 = [r for r in rows if r["seed"] == first_seed]
    ax.plot([r["train_wall_s"] / 60 for r in s0], [r["missing_cells"] for r in s0], "o-")
    ax.set_yscale("symlog", linthresh=1)
    # symlog labels only decades: runs whose counts stay within one (3-6 cells, say) got no labels
    top = max([r["missing_cells"] for r in s0], default=1)
    ax.set_yticks([v for v in CELL_TICKS if v <= max(top, 1)])
    ax.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
    ax.yaxis.set_minor_locator(matplotlib.ticker.NullLocator())
    ax.set_xlabel("training wall time [min]")
    ax.set_ylabel("site-matrix cells missing a bar")
    ax.set_title(f"{a.run.name}: cells missing a bar (seed {first_seed}, 66 cells)", fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(a.out.with_suffix(".png"), dpi=110)


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
