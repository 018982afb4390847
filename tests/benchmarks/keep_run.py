"""Trim a `slinger train` run brought back from a GPU machine to what policies/training keeps.

``python -m tests.benchmarks.keep_run runs/<name> [--rows N ...] [--candidates N ...] [--dry-run]``

A run that ``tests/benchmarks/device_runs.sh collect`` brought back holds every site matrix the gate
ran with each throw's landing (``per_throw``, about 160 kB a matrix), the matrices' plots, every
candidate the gate exported and the TensorBoard event directory. The runs kept in the tree
(policies/training/README.md) hold:

* per-throw rows only in the matrices of the iterations that decide the run (:func:`row_iterations`:
  the first and last the gate judged, the far-target style's (the last at or before iteration 250,
  tests/benchmarks/training_throw_style.py), every one that met every bar on every gate seed, the
  exported policy's) and in every matrix of a held-out seed (one outside the gate's seeds, run after
  the run); the other matrices keep their per-cell statistics and verdicts;
* no matrix plots (the JSON and the Markdown tables carry the same figures);
* of the gate's exported candidates (``candidates/checkpoint_<N>.onnx`` and ``.json``) those that
  decide the run and are not its export (:func:`candidate_iterations`), and no ``.pt`` but the
  candidate of the pass a run past the bars exports (:func:`chosen_pass`, with its ONNX file and
  manifest, its export or not): a run resumed past the bars can export that pass only with its
  checkpoint there (sim_twin.training.matrix_gate.MatrixGate.exportable_passes);
* the TensorBoard events as ``tb.tar.gz`` (``tar xzf tb.tar.gz && tensorboard --logdir tb``).

``--rows`` and ``--candidates`` keep more. The checkpoint, config, curve, gate verdicts, logs and the
export are left as they are. Prints what it removed and the run's size before and after.
"""

from __future__ import annotations

import argparse
import json
import shutil
import tarfile
from dataclasses import dataclass
from pathlib import Path

STYLE_ITERATION_MAX = 250
"""The far-target style is read from the gate's last seed-0 matrix at or before this iteration
(tests/benchmarks/training_throw_style.py)."""


def load_gate(run: Path) -> dict:
    """The run's ``matrices/matrix_gate.json``. Raises FileNotFoundError for a run without a gate."""
    path = run / "matrices" / "matrix_gate.json"
    if not path.exists():
        raise FileNotFoundError(f"{run} has no matrices/matrix_gate.json: not a run with a site-matrix gate")
    return json.loads(path.read_text())


def exported_iteration(run: Path) -> int | None:
    """The iteration of the run's exported policy (its model card's), or None without one."""
    cards = sorted(run.glob("throw*.card.json"))
    return int(json.loads(cards[0].read_text())["iteration"]) if cards else None


@dataclass(frozen=True)
class RunDecision:
    """What decides a run, read once: its gate's state (``matrix_gate.json``), the first iteration met
    on every gate seed (None if none) and its exported policy's iteration (None without an export)."""

    gate: dict
    first_pass: int | None
    exported: int | None


def decide(run: Path) -> RunDecision:
    """The run's :class:`RunDecision`. The first pass counts the gate's verdicts and a gate seed's matrix
    in ``matrices/`` that the gate holds no verdict of (one run after the run, as ``throw2d-scratch-g1``'s
    iteration 575 on seed 1), read as training_run_report reads them (``after_run_row``, ``first_pass``).

    Raises:
        FileNotFoundError: ``run`` has no ``matrices/matrix_gate.json``.
    """
    from tests.benchmarks.training_run_report import after_run_row, first_pass, train_wall_s

    gate = load_gate(run)
    rows = [{**r, "after_run": False} for r in gate["results"]]
    judged = {(r["iteration"], r["seed"]) for r in rows}
    later = []
    for m in sorted((run / "matrices").glob("site_matrix_*_it*.json")):
        it, seed = _iteration_and_seed(m)
        if seed in gate["seeds"] and (it, seed) not in judged:
            later.append(m)
    if later:
        wall = train_wall_s(run)
        rows += [after_run_row(run, m, wall) for m in later]
    first = first_pass(rows, gate["seeds"])
    return RunDecision(gate, first["iteration"] if first else None, exported_iteration(run))


def row_iterations(d: RunDecision) -> set[int]:
    """The iterations whose matrices keep their per-throw rows (module docstring), every checkpoint
    that met every bar on every gate seed among them: the paired test against the deployed policy
    that ranks a run's passes (sim_twin.training.matrix_gate.choose_pass) reads the rows, so it can be
    run again on any of them."""
    judged = sorted({r["iteration"] for r in d.gate["results"]})
    keep = {judged[0], judged[-1]} if judged else set()
    early = [it for it in judged if it <= STYLE_ITERATION_MAX]
    if early:
        keep.add(early[-1])
    from sim_twin.training.matrix_gate import saved_passes

    passes = {int(p["iteration"]) for p in saved_passes(d.gate)}
    return keep | passes | {it for it in (d.first_pass, d.exported) if it is not None}


def chosen_pass(d: RunDecision) -> int | None:
    """The iteration of the pass a run past the bars exports (sim_twin.training.matrix_gate.choose_pass
    over the gate's saved passes); None where no checkpoint passed."""
    from sim_twin.training.matrix_gate import choose_pass, saved_passes

    chosen = choose_pass(saved_passes(d.gate))
    return int(chosen["iteration"]) if chosen else None


def candidate_iterations(d: RunDecision) -> set[int]:
    """The gate's candidates kept beside the export: the first that met every bar on every gate seed
    and the one a run past the bars exports (:func:`chosen_pass`), where they are not the export, or,
    where none met them, the last two the gate judged."""
    if d.first_pass is not None:
        return {it for it in (d.first_pass, chosen_pass(d)) if it and it != d.exported}
    return set(sorted({r["iteration"] for r in d.gate["results"]})[-2:])


def _iteration_and_seed(path: Path) -> tuple[int, int]:
    from sim_twin.training.matrix_gate import parse_matrix_file_name

    return parse_matrix_file_name(path.name)


def _size(path: Path) -> int:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file())


def keep_run(run: Path, rows: set[int] = frozenset(), candidates: set[int] = frozenset(), dry_run: bool = False,
             decision: RunDecision | None = None) -> list[str]:
    """Trim ``run`` in place (module docstring); ``rows`` and ``candidates`` add iterations to keep;
    ``decision`` is the run's :func:`decide` where the caller has it. Returns what it did, one line per
    file or directory. With ``dry_run`` it changes nothing.

    Raises:
        FileNotFoundError: ``run`` has no ``matrices/matrix_gate.json``.
    """
    d = decision or decide(run)
    gate = d.gate
    keep_rows = row_iterations(d) | set(rows)
    keep_cands = candidate_iterations(d) | set(candidates)
    resume = chosen_pass(d)  # its .pt too (module docstring)
    done = []
    for m in sorted((run / "matrices").glob("site_matrix_*_it*.json")):
        it, seed = _iteration_and_seed(m)
        if it in keep_rows or seed not in gate["seeds"]:
            continue
        rep = json.loads(m.read_text())
        cells = [t for p in rep["profiles"] for t in p["targets"] if "per_throw" in t]
        if cells:
            done.append(f"per-throw rows dropped: {m.relative_to(run)}")
            if not dry_run:
                for t in cells:
                    del t["per_throw"]
                m.write_text(json.dumps(rep, indent=1) + "\n")
    for png in sorted((run / "matrices").glob("*.png")):
        done.append(f"removed: {png.relative_to(run)}")
        if not dry_run:
            png.unlink()
    cand_dir = run / "candidates"
    for f in sorted(cand_dir.glob("checkpoint_*")) if cand_dir.is_dir() else []:
        it = int(f.name.split("_")[1].split(".")[0])
        if it != resume and (f.suffix == ".pt" or it not in keep_cands):
            done.append(f"removed: {f.relative_to(run)}")
            if not dry_run:
                f.unlink()
    if cand_dir.is_dir() and not dry_run and not any(cand_dir.iterdir()):
        cand_dir.rmdir()
    tb = run / "tb"
    if tb.is_dir():
        done.append("tb/ packed as tb.tar.gz" + (" (beside the one there)" if (run / "tb.tar.gz").exists() else ""))
        if not dry_run:
            target = run / ("tb.tar.gz" if not (run / "tb.tar.gz").exists() else "tb.more.tar.gz")
            with tarfile.open(target, "w:gz") as tar:
                tar.add(tb, arcname="tb")
            shutil.rmtree(tb)
    return done


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", type=Path, nargs="+", help="run directories brought back by device_runs.sh collect")
    p.add_argument("--rows", type=int, nargs="*", default=[], help="more iterations whose matrices keep per-throw rows")
    p.add_argument("--candidates", type=int, nargs="*", default=[], help="more gate candidates to keep")
    p.add_argument("--dry-run", action="store_true", help="say what would go, change nothing")
    a = p.parse_args()
    for run in a.runs:
        before, d = _size(run), decide(run)
        done = keep_run(run, set(a.rows), set(a.candidates), a.dry_run, d)
        print(f"{run}: rows kept in iterations {sorted(row_iterations(d) | set(a.rows))}, candidates kept "
              f"{sorted(candidate_iterations(d) | set(a.candidates))}; {len(done)} changes"
              + ("" if a.dry_run else f"; {before / 2**20:.1f} MiB -> {_size(run) / 2**20:.1f} MiB"))
        for line in done:
            print("  " + line)


if __name__ == "__main__":
    main()
