"""What follows a `slinger train` run that met the bars, here on the CPU host: held-out start-pose seeds
and the paired deploy test, for the checkpoints that decide the run.

``python -m tests.benchmarks.after_run policies/training/<run> [--held-out 2] [--workers 2] [--dry-run]``

For the run's first checkpoint to meet every bar on every gate seed and for its exported policy
(tests/benchmarks/keep_run.py ``decide``; the gate's export
``candidates/checkpoint_<N>.onnx`` or ``throw<mode>.onnx``), or, for a run stopped before its export,
the pass its finish would have exported (``deciding_policies``), it

1. runs the site matrix on each held-out seed that the run lacks, with the gate's own command
   (``python -m sim_twin.evaluation.cli --policy <onnx> --matrix --seed S --throws <the gate's> --workers W
   --out <run>/matrices/site_matrix_<mode>_it<N>_seed<S>.json``; about 3 minutes a matrix with 2
   workers on the 2-core host);
2. writes the paired deploy test against the deployed policy's committed matrices of the same seeds
   (``reports/site_matrix_<mode>[_seed<S>].json``; sim_twin.evaluation.matrix_compare) to
   ``<run>/compare_with_deployed.txt`` for the export and ``compare_with_deployed_it<N>.txt`` for a
   first pass that is not the export, its first line the command that made it.

A run that met nothing has nothing to follow. ``--dry-run`` prints the commands and runs none. The
report that cites the matrices is ``python -m tests.benchmarks.training_run_report ... --after-run``.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import subprocess
import sys
from pathlib import Path

from sim_twin.evaluation import matrix_compare

from tests.benchmarks.keep_run import RunDecision, chosen_pass, decide


def deciding_policies(run: Path, d: RunDecision | None = None) -> dict[int, Path]:
    """{iteration: ONNX file} of the run's first pass and its export (module docstring), and for a run
    stopped before its export (the device time) the pass its finish would have exported
    (keep_run.chosen_pass, the one keep_run keeps) where its ONNX file is in the
    run; {} for a run that met no bar on every gate seed and exported nothing.

    ``d`` is the run's keep_run.decide where the caller has it.

    Raises:
        FileNotFoundError: the run has no gate (keep_run) or a deciding checkpoint's ONNX file is gone.
    """
    d = d or decide(run)
    out = {}
    if d.exported is not None:
        out[d.exported] = next(run.glob("throw*.onnx"))
    if d.first_pass is not None and d.first_pass not in out:
        out[d.first_pass] = run / "candidates" / f"checkpoint_{d.first_pass}.onnx"
    chosen = chosen_pass(d) if d.exported is None else None
    if chosen is not None:
        onnx = run / "candidates" / f"checkpoint_{chosen}.onnx"
        if onnx.exists():  # runs kept before keep_run kept it lack it (-l0)
            out.setdefault(chosen, onnx)
    for it, onnx in out.items():
        if not onnx.exists():
            raise FileNotFoundError(f"{onnx}: the ONNX file of iteration {it} is not in the run")
    return out


def matrix_path(run: Path, mode: str, iteration: int, seed: int) -> Path:
    """The gate's file name of a site matrix (sim_twin.training.matrix_gate.matrix_file_name)."""
    from sim_twin.training.matrix_gate import matrix_file_name

    return run / "matrices" / matrix_file_name(mode, iteration, seed)


def deployed_matrix(root: Path, mode: str, seed: int) -> Path:
    """The deployed policy's committed site matrix of ``seed`` (reports/site_matrix_<mode>[_seed<S>].json)."""
    return root / "reports" / (f"site_matrix_{mode}.json" if seed == 0 else f"site_matrix_{mode}_seed{seed}.json")


def plan(run: Path, held_out: list[int], workers: int, root: Path) -> list[tuple[list[str], Path | None]]:
    """The commands, in order: (argv, None) for a matrix to run, (argv, file) for a comparison whose
    output goes to ``file``. Matrices already in the run are not run again."""
    d = decide(run)
    mode, gate_seeds = d.gate["mode"], d.gate["seeds"]
    seeds = list(gate_seeds) + [s for s in held_out if s not in gate_seeds]
    steps: list[tuple[list[str], Path | None]] = []
    for it, onnx in sorted(deciding_policies(run, d).items()):
        for s in held_out:
            out = matrix_path(run, mode, it, s)
            if not out.exists():
                steps.append(([sys.executable, "-m", "sim_twin.evaluation.cli", "--policy", str(onnx), "--matrix", "--seed", str(s),
                               "--throws", str(d.gate["throws"]), "--workers", str(workers), "--out", str(out)], None))
        cmp = [sys.executable, "-m", "sim_twin.evaluation.matrix_compare",
               "--deployed", *(str(deployed_matrix(root, mode, s).relative_to(root)) for s in seeds),
               "--candidate", *(str(matrix_path(run, mode, it, s)) for s in seeds)]
        steps.append((cmp, run / ("compare_with_deployed.txt" if it == d.exported else f"compare_with_deployed_it{it}.txt")))
    return steps


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run", type=Path)
    p.add_argument("--held-out", type=int, nargs="+", default=[2], help="start-pose seeds the gate did not use (default 2)")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--dry-run", action="store_true")
    a = p.parse_args()
    root = Path(__file__).resolve().parents[2]
    try:
        steps = plan(a.run, a.held_out, a.workers, root)
    except FileNotFoundError as e:
        raise SystemExit(f"after_run: {e}") from None
    if not steps:
        print(f"{a.run}: no checkpoint met every bar and nothing was exported: nothing to follow")
    for argv, out in steps:
        shown = "python " + " ".join(argv[1:])
        print(shown + (f" > {out}" if out else ""), flush=True)
        if a.dry_run:
            continue
        if out is None:
            subprocess.run(argv, check=True, cwd=root)
        else:  # in this process: its paths relative to the repository root
            buf = io.StringIO()
            with contextlib.redirect_stdout(buf):
                code = matrix_compare.main([str(root / x) if not Path(x).is_absolute() and (root / x).exists() else x for x in argv[3:]])
            if code not in (0, 1):  # 1: worse on a cell, a verdict, not an error
                raise SystemExit(f"matrix_compare failed ({code}) on {out}")
            out.write_text(f"# {shown}\n{buf.getvalue()}")
            print(buf.getvalue().strip().splitlines()[-1])


if __name__ == "__main__":
    main()
