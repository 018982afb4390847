"""Which throw style a 2D from-scratch run settled on, and whether it met the bars.

``python tests/benchmarks/training_throw_style.py RUN ... --out reports/<name>`` reads each run's
site-matrix gate (``matrices/matrix_gate.json`` and the seed-0 matrices beside it) and writes
``<name>.json`` and ``<name>.md``: per run the training seed, the discount γ, the nominal
far-target throw's mean duration (start to landing, ``mean_duration_s`` of the site matrix) and
downrange σ at 10 m in the last seed-0 matrix judged by iteration ``STYLE_BY_ITERATION``, and the
gate's outcome (bars met on every gate seed, at what training wall time, or the cells still
missing at the last verdict).

A run is given as a directory (``policies/training/throw2d-scratch-u``, an unpacked device tar) or
as ``REV:PATH`` for a run kept only in git history (``lab-notebook-2026-11-25:policies/training/
throw2d-scratch-v``; docs/training.md "Why a run stalls").

The far-target throws of the from-scratch runs come in two styles, fixed within the first
~250 iterations: a nominal 10 m throw lasting about 3.8-4.2 s ("long") or 2.7-3.5 s ("short");
``LONG_STYLE_S`` separates them.
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import re
import subprocess
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from sim_twin.evaluation.matrix import cell_bars
from sim_twin.training.matrix_gate import saved_passes

STYLE_BY_ITERATION = 250
"""The style is read from the last seed-0 matrix judged at or before this iteration (~7 min)."""
LONG_STYLE_S = 3.6
"""Nominal 10 m throws lasting at least this long [s] are the long style."""
FAR_TARGET_M = 10.0
_MATRIX = re.compile(r"site_matrix_2d_it(\d+)\.json$")  # seed 0 (other seeds carry a _seed<S> suffix)


def kept_rows(report: Path, settings: dict, runs: list[str], rows_key: str = "rows") -> list[dict]:
    """The rows of the earlier ``report`` (its JSON) whose runs are not among ``runs`` (run specs,
    compared by the run's directory name, :class:`RunSource`), to stand beside an invocation's new rows
    (a report script's ``--keep-rows-of``: each run takes minutes on a CPU).

    ``settings`` maps report entries to the values this invocation uses (episodes, noise, PRNG key,
    target distance): the rows of a report made otherwise cannot stand beside the new ones.

    Raises:
        ValueError: the report has another value for one of ``settings``.
    """
    old = json.loads(report.read_text())
    for name, want in settings.items():
        if old.get(name) != want:
            raise ValueError(f"{report}: {name} {old.get(name)} differs from this run's {want}; its rows cannot stand beside these")
    now = {RunSource(spec).name for spec in runs}
    return [r for r in old[rows_key] if r["run"] not in now]


class RunSource:
    """Files of one run: a directory, or ``REV:PATH`` read from git (``git show``)."""

    def __init__(self, spec: str, repo: Path = Path(".")):
        self.spec, self.repo = spec, repo
        self.rev, _, path = spec.rpartition(":") if ":" in spec and not Path(spec).exists() else ("", "", spec)
        self.path = Path(path)
        if not self.rev and not self.path.is_dir():
            raise FileNotFoundError(f"{spec}: no such run directory (give REV:PATH for a run kept in git only)")

    @property
    def name(self) -> str:
        return self.path.name

    def read(self, rel: str) -> str:
        """Text of the run's file ``rel``. Raises FileNotFoundError where it has none."""
        return self.read_bytes(rel).decode()

    def read_bytes(self, rel: str) -> bytes:
        """Contents of the run's file ``rel`` (a checkpoint, say). Raises FileNotFoundError where it has none."""
        if not self.rev:
            f = self.path / rel
            if not f.is_file():
                raise FileNotFoundError(f"{self.spec}: no {rel}")
            return f.read_bytes()
        r = subprocess.run(["git", "-C", str(self.repo), "show", f"{self.rev}:{self.path.as_posix()}/{rel}"],
                           capture_output=True)
        if r.returncode:
            raise FileNotFoundError(f"{self.spec}: no {rel} ({r.stderr.decode().strip()})")
        return r.stdout

    def list(self, rel: str) -> list[str]:
        """Names of the files in the run's folder ``rel``."""
        if not self.rev:
            d = self.path / rel
            return sorted(p.name for p in d.iterdir()) if d.is_dir() else []
        r = subprocess.run(["git", "-C", str(self.repo), "ls-tree", "--name-only", self.rev, f"{self.path.as_posix()}/{rel}/"],
                           capture_output=True, text=True, check=True)
        return sorted(Path(x).name for x in r.stdout.split())


def nominal_cell(matrix: dict, target_m: float = FAR_TARGET_M) -> dict:
    """The nominal profile's cell at ``target_m`` of a site matrix, as the matrix holds it.

    Raises:
        ValueError: the matrix has no nominal cell at that target.
    """
    for p in matrix["profiles"]:
        if p["name"] == "nominal":
            for t in p["targets"]:
                if abs(t["target_m"] - target_m) < 1e-6:
                    return t
    raise ValueError(f"site matrix {matrix.get('policy_version', '?')} has no nominal cell at {target_m} m")


def far_throw(matrix: dict, target_m: float = FAR_TARGET_M) -> dict:
    """The nominal profile's cell at ``target_m`` of a site matrix: {duration_s, sigma_m, bias_m}.

    Raises:
        ValueError: the matrix has no nominal cell at that target.
    """
    t = nominal_cell(matrix, target_m)
    return {"duration_s": t["mean_duration_s"], "sigma_m": t["sigma_downrange_m"], "bias_m": t["bias_m"]}


def seed0_iterations(src: RunSource) -> list[int]:
    """Iterations of the run's seed-0 gate matrices (``matrices/site_matrix_2d_it<N>.json``), ascending."""
    return sorted(int(m.group(1)) for n in src.list("matrices") if (m := _MATRIX.search(n)))


def seed0_matrices(src: RunSource, iterations: tuple[int, int]) -> list[tuple[int, dict]]:
    """(iteration, matrix) of the run's seed-0 gate matrices from ``iterations[0]`` to ``iterations[1]``
    (inclusive), ascending."""
    return [(it, json.loads(src.read(f"matrices/site_matrix_2d_it{it}.json")))
            for it in seed0_iterations(src) if iterations[0] <= it <= iterations[1]]


def style_of(duration_s: float) -> str:
    """'long' or 'short' (LONG_STYLE_S)."""
    return "long" if duration_s >= LONG_STYLE_S else "short"


def run_style(src: RunSource, by_iteration: int = STYLE_BY_ITERATION) -> dict:
    """One run's row: name, training seed, gamma, the style checkpoint's iteration, wall time,
    nominal 10 m duration, σ and style, and the gate's outcome ({met, iteration, train_wall_min}
    or {met: False, last_iteration, last_train_wall_min, missing_cells}).

    The style is read from the last seed-0 matrix by ``by_iteration``, or, where its nominal 10 m
    throws did not land (``mean_duration_s`` None), from the first later one where they did.

    Raises:
        FileNotFoundError: no gate record or no seed-0 matrix by ``by_iteration``.
        ValueError: no seed-0 matrix in which a nominal 10 m throw landed.
    """
    try:
        cfg = json.loads(src.read("config.json"))
    except FileNotFoundError:
        cfg = {}  # an early run kept no config: its README names the recipe
    gate = json.loads(src.read("matrices/matrix_gate.json"))
    seed0 = seed0_iterations(src)
    early = [i for i in seed0 if i <= by_iteration]
    if not early:
        raise FileNotFoundError(f"{src.spec}: no seed-0 site matrix by iteration {by_iteration}")
    # the last matrix by the iteration; where its nominal far throws did not land (a run still holding
    # them, whose next matrix came later), the first later one where they did: an earlier matrix is
    # from before the styles split
    for it in [early[-1]] + [i for i in seed0 if i > by_iteration]:
        far = far_throw(json.loads(src.read(f"matrices/site_matrix_2d_it{it}.json")))
        if far["duration_s"] is not None:
            break
    else:
        raise ValueError(f"{src.spec}: no seed-0 site matrix where a nominal 10 m throw landed")
    wall = {r["iteration"]: r["train_wall_s"] for r in gate["results"]}
    passed = saved_passes(gate)
    if passed:
        first = min(passed, key=lambda p: p["iteration"])
        outcome = {"met": True, "iteration": first["iteration"], "train_wall_min": round(first["train_wall_s"] / 60, 1)}
    else:
        last = max(r["iteration"] for r in gate["results"])
        at_last = [r for r in gate["results"] if r["iteration"] == last]
        outcome = {"met": False, "last_iteration": last, "last_train_wall_min": round(at_last[0]["train_wall_s"] / 60, 1),
                   "missing_cells": {str(r["seed"]): r["missing_cells"] for r in at_last}}
    return {
        "run": src.name, "source": src.spec, "training_seed": cfg.get("training", {}).get("seed"),
        "gamma": cfg.get("runner", {}).get("algorithm", {}).get("gamma"), "num_envs": cfg.get("num_envs"),
        "release_bias_init": cfg.get("training", {}).get("release_bias_init"),
        "style_iteration": it, "style_train_wall_min": round(wall.get(it, float("nan")) / 60, 1),
        "far_duration_s": round(far["duration_s"], 2), "far_sigma_m": round(far["sigma_m"], 3), "style": style_of(far["duration_s"]),
        "outcome": outcome,
    }


SPLIT_TERMS = ("mean_episode_length", "impact_err_m", "reward_delta_err", "reward_landing", "reward_landing_fine",
               "reward_act_diff", "reward_no_release")
"""curve.csv columns compared between the styles: per-step means over the iteration's episodes
(reward terms weighted as in the recipe), the episode length in control steps and the mean
training impact error, m."""
SPLIT_ITERATIONS = (50, 100, 150, 200, 250)


def curve_at(src: RunSource, iterations: tuple[int, ...] = SPLIT_ITERATIONS) -> dict[int, dict[str, float]]:
    """The run's curve.csv row at (the first logged row at or after) each of ``iterations``:
    {iteration: {column: value}}; iterations past the curve's end are left out.

    Raises:
        FileNotFoundError: the run has no curve.csv.
    """
    rows = list(csv.DictReader(io.StringIO(src.read("curve.csv"))))
    out = {}
    for it in iterations:
        at = [r for r in rows if float(r["iteration"]) >= it]
        if at:
            out[it] = {k: float(v) for k, v in at[0].items() if v not in ("", None)}
    return out


def term_split(rows: list[dict], curves: list[dict[int, dict[str, float]]],
               terms: tuple[str, ...] = SPLIT_TERMS) -> list[dict]:
    """Whether a training-curve column separates the long-style runs from the short ones at each
    iteration: per (term, iteration) the range over each style's runs and ``separates`` (the two
    ranges do not overlap). NaN values (a term no episode paid) are skipped. ``rows`` are
    run_style rows and ``curves`` their curve_at, in the same order."""
    out = []
    for term in terms:
        for it in sorted({i for c in curves for i in c}):
            vals: dict[str, list[float]] = {"long": [], "short": []}
            for row, curve in zip(rows, curves, strict=True):
                v = curve.get(it, {}).get(term)
                if v is not None and v == v:
                    vals[row["style"]].append(v)
            if vals["long"] and vals["short"]:
                lo_l, hi_l, lo_s, hi_s = min(vals["long"]), max(vals["long"]), min(vals["short"]), max(vals["short"])
                out.append({"term": term, "iteration": it, "long": [lo_l, hi_l], "short": [lo_s, hi_s],
                            "runs": [len(vals["long"]), len(vals["short"])], "separates": hi_l < lo_s or hi_s < lo_l})
    return out


SPREAD_ITERATIONS = (300, 1300)
"""Iterations whose seed-0 matrices enter the duration-spread table: from the curriculum stage (300) to
about 20 minutes of training (~1300 on one H200)."""
SIGMA_BAR_M = 0.10
"""The nominal 2D cell's σ downrange bar [m] (sim_twin.evaluation.matrix.cell_bars)."""
SPREAD_EDGES_S = (3.6, 4.0, 4.3, 4.6)
"""Nominal 10 m throw durations [s] between the duration-spread table's bins."""


def duration_spread(src: RunSource, iterations: tuple[int, int] = SPREAD_ITERATIONS) -> list[dict]:
    """Every seed-0 gate matrix of the run from ``iterations[0]`` to ``iterations[1]`` (inclusive) whose
    nominal 10 m throws landed: [{run, iteration, duration_s, sigma_m, bias_m, accuracy}], ``accuracy``
    the cell's accuracy bar (sim_twin.evaluation.matrix.cell_bars: |bias| and σ downrange ≤ 0.10 m);
    a run without gate matrices gives []."""
    out = []
    for it, matrix in seed0_matrices(src, iterations):
        cell = nominal_cell(matrix)
        if cell.get("mean_duration_s") is None or not cell.get("landed"):
            continue
        out.append({"run": src.name, "iteration": it, "duration_s": round(cell["mean_duration_s"], 3),
                    "sigma_m": round(cell["sigma_downrange_m"], 4), "bias_m": round(cell["bias_m"], 4),
                    "accuracy": cell_bars("2d", "nominal", False, cell)["accuracy"]})
    return out


LATER_SWING_S = 3.2
"""A nominal cell whose throws last this long on average [s] (start to landing) is thrown mostly on a later
swing: first-swing throws of 7.5-10 m last 2.0-2.7 s and later-swing ones 3.6-4.9 s in the runs' matrices
(tests/benchmarks/spread_sources.py splits them by the release command's time)."""


def swing_switch(src: RunSource, iterations: tuple[int, int] = SPREAD_ITERATIONS) -> dict:
    """Where the run's nominal throws change from the first swing to a later one: per seed-0 gate matrix
    from ``iterations[0]`` to ``iterations[1]``, the nearest target whose nominal throws last LATER_SWING_S
    or more on average (None where none does), and their median over the matrices (None where none has one):
    {"run", "per_matrix": {iteration: target_m | None}, "median_target_m"}."""
    per = {}
    for it, matrix in seed0_matrices(src, iterations):
        nominal = next(p for p in matrix["profiles"] if p["name"] == "nominal")
        per[it] = next((t["target_m"] for t in sorted(nominal["targets"], key=lambda t: t["target_m"])
                        if t.get("mean_duration_s") is not None and t["mean_duration_s"] >= LATER_SWING_S), None)
    found = [v for v in per.values() if v is not None]
    return {"run": src.name, "per_matrix": per, "median_target_m": float(np.median(found)) if found else None}


def spread_by_duration(points: list[dict], edges: tuple[float, ...] = SPREAD_EDGES_S) -> list[dict]:
    """duration_spread points binned by the 10 m throw's duration at ``edges`` [s]: per bin {lo_s, hi_s
    (None at the open ends), matrices, runs, median_sigma_m, sigma_share, accuracy_share}: the shares of
    the bin's matrices whose nominal 10 m σ downrange is within its 0.10 m bar and whose cell met its
    whole accuracy bar (σ and bias); None for an empty bin."""
    bounds = [None, *edges, None]
    rows = []
    for lo, hi in zip(bounds[:-1], bounds[1:], strict=True):
        inside = [p for p in points if (lo is None or p["duration_s"] >= lo) and (hi is None or p["duration_s"] < hi)]
        sig = sorted(p["sigma_m"] for p in inside)
        rows.append({"lo_s": lo, "hi_s": hi, "matrices": len(inside), "runs": len({p["run"] for p in inside}),
                     "median_sigma_m": None if not sig else round(float(np.median(sig)), 3),
                     "sigma_share": None if not inside else round(sum(p["sigma_m"] <= SIGMA_BAR_M for p in inside) / len(inside), 2),
                     "accuracy_share": None if not inside else round(sum(p["accuracy"] for p in inside) / len(inside), 2)})
    return rows


def plot_spread(points: list[dict], rows: list[dict], path: Path) -> None:
    """σ downrange of the nominal 10 m cell against its mean throw duration, one dot per seed-0 matrix,
    filled where the run met every bar on the gate seeds (``rows``: run_style rows), the 0.10 m bar
    dashed; matplotlib, to ``path``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    met = {r["run"] for r in rows if r["outcome"]["met"]}
    fig, ax = plt.subplots(figsize=(7, 4.5))
    for ok, style in ((True, {"color": "tab:blue", "label": "run met every bar"}),
                      (False, {"facecolors": "none", "edgecolors": "tab:red", "label": "run did not"})):
        sel = [p for p in points if (p["run"] in met) == ok]
        ax.scatter([p["duration_s"] for p in sel], [p["sigma_m"] for p in sel], s=18, **style)
    ax.axhline(SIGMA_BAR_M, ls="--", color="grey", lw=1, label="nominal σ bar 0.10 m")
    for e in SPREAD_EDGES_S:
        ax.axvline(e, ls=":", color="lightgrey", lw=1)
    ax.set_xlabel("nominal 10 m throw: mean duration, start to landing [s]")
    ax.set_ylabel("nominal 10 m: σ downrange [m]")
    ax.set_title(f"Seed-0 gate matrices, iterations {SPREAD_ITERATIONS[0]}-{SPREAD_ITERATIONS[1]}, {len(met)} of {len(rows)} runs met (at any time)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def outcome_text(o: dict) -> str:
    """The gate's outcome of a run_style row in words."""
    if o["met"]:
        return f"every bar on the gate seeds at iteration {o['iteration']}, {o['train_wall_min']} min"
    cells = ", ".join(f"seed {k}: {v} cells short" for k, v in o["missing_cells"].items())
    return f"not met; last verdict at iteration {o['last_iteration']}, {o['last_train_wall_min']} min ({cells})"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="run directories or REV:PATH")
    p.add_argument("--out", type=Path, required=True, help="report stem (writes .json and .md)")
    p.add_argument("--by-iteration", type=int, default=STYLE_BY_ITERATION)
    p.add_argument("--spread", action="store_true",
                   help="add the duration-spread table (SPREAD_ITERATIONS, SPREAD_EDGES_S) and its plot, <out>_spread.png")
    args = p.parse_args()
    sources = [RunSource(s) for s in args.runs]
    rows = [run_style(src, args.by_iteration) for src in sources]
    same_recipe = [i for i, r in enumerate(rows) if r["num_envs"] == 65536]  # the recipe's environment count
    split = term_split([rows[i] for i in same_recipe], [curve_at(sources[i]) for i in same_recipe])
    from sim_twin.provenance import git_commit

    commit = git_commit()
    report = {"date": datetime.now(UTC).isoformat(timespec="seconds"), "commit": commit,
              "long_style_s": LONG_STYLE_S, "by_iteration": args.by_iteration, "far_target_m": FAR_TARGET_M, "runs": rows,
              "term_split": {"runs": [rows[i]["run"] for i in same_recipe], "by_term": split}}
    if args.spread:
        points = [pt for src in sources for pt in duration_spread(src)]
        report["duration_spread"] = {"iterations": list(SPREAD_ITERATIONS), "edges_s": list(SPREAD_EDGES_S),
                                     "bins": spread_by_duration(points), "points": points,
                                     "swing_switch": [swing_switch(src) for src in sources]}
        plot_spread(points, rows, args.out.parent / f"{args.out.name}_spread.png")
    args.out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    md = ["# 2D from-scratch runs: far-target throw style against the gate's outcome\n",
          f"Date {report['date']}, commit `{commit}`. Style: the nominal {FAR_TARGET_M:g} m throw's mean duration "
          f"(start to landing) in the last seed-0 gate matrix judged by iteration {args.by_iteration}; long ≥ {LONG_STYLE_S} s.\n",
          "| run | γ | envs | release bias | training seed | style read at | 10 m duration | 10 m σ | style | outcome |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        md.append(f"| `{r['run']}` | {r['gamma'] or '-'} | {r['num_envs'] or '-'} | {'-' if r['release_bias_init'] is None else r['release_bias_init']} | {'-' if r['training_seed'] is None else r['training_seed']} | it {r['style_iteration']} "
                  f"({r['style_train_wall_min']} min) | {r['far_duration_s']} s | {r['far_sigma_m']} m | {r['style']} | {outcome_text(r['outcome'])} |")
    md += ["", f"## Do the training curves show the split? ({len(same_recipe)} runs with 65536 environments)\n",
           "Per-step means from each run's curve.csv; a term separates the styles at an iteration when the "
           "long runs' range and the short runs' range do not overlap.\n",
           "| term | " + " | ".join(f"it {i}: long / short" for i in SPLIT_ITERATIONS) + " |",
           "|---|" + "---|" * len(SPLIT_ITERATIONS)]
    for term in SPLIT_TERMS:
        cells = []
        for it in SPLIT_ITERATIONS:
            c = next((x for x in split if x["term"] == term and x["iteration"] == it), None)
            cells.append("-" if c is None else f"{c['long'][0]:.3g}-{c['long'][1]:.3g} / {c['short'][0]:.3g}-{c['short'][1]:.3g}"
                         + (" **separates**" if c["separates"] else ""))
        md.append(f"| {term} | " + " | ".join(cells) + " |")
    if args.spread:
        ds = report["duration_spread"]
        md += ["", f"## The 10 m throw's duration and its spread (seed-0 matrices, iterations {SPREAD_ITERATIONS[0]}-{SPREAD_ITERATIONS[1]})\n",
               "Every seed-0 gate matrix of these runs in that span whose nominal 10 m throws landed, binned by the throw's "
               f"mean duration; the accuracy bar is |bias| and σ ≤ 0.10 m. Plot: `{args.out.name}_spread.png`.\n",
               "| 10 m throw duration | matrices | runs | median σ | σ ≤ 0.10 m | accuracy bar met (σ and bias) |", "|---|---|---|---|---|---|"]
        for b in ds["bins"]:
            span = f"< {b['hi_s']} s" if b["lo_s"] is None else (f"≥ {b['lo_s']} s" if b["hi_s"] is None else f"{b['lo_s']}-{b['hi_s']} s")
            pct = {k: "-" if b[k] is None else f"{b[k]:.0%}" for k in ("sigma_share", "accuracy_share")}
            md.append(f"| {span} | {b['matrices']} | {b['runs']} | {'-' if b['median_sigma_m'] is None else b['median_sigma_m']} m | "
                      f"{pct['sigma_share']} | {pct['accuracy_share']} |")
        md += ["", f"## Where the nominal throws change to a later swing (seed-0 matrices, iterations {SPREAD_ITERATIONS[0]}-{SPREAD_ITERATIONS[1]})\n",
               f"Per matrix the nearest target whose nominal throws last {LATER_SWING_S} s or more on average (start to landing), "
               "the median over the matrices; the outcome as above.\n",
               "| run | median switch target | per matrix | outcome |", "|---|---|---|---|"]
        for row, sw in zip(rows, ds["swing_switch"], strict=True):
            per = " ".join(f"{it}: {'-' if t is None else f'{t:g} m'}" for it, t in sw["per_matrix"].items())
            med = "-" if sw["median_target_m"] is None else f"{sw['median_target_m']:g} m"
            md.append(f"| `{row['run']}` | {med} | {per or '-'} | {outcome_text(row['outcome'])} |")
    args.out.with_suffix(".md").write_text("\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
