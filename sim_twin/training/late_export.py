"""Export and card the passing checkpoint a run exports, after the run, where its machine went back first.

``python -m sim_twin.training.late_export RUN_DIR --command "slinger train ..." --commit SHA [--first | --iteration N]``

``slinger train --no-stop-at-bars`` exports the newest checkpoint that met every bar (or with
``--gate-compare-with`` the one worse than the deployed policy on the fewest cells) when it finishes
(sim_twin.training.train.TrainingRun.finish). A run on a lent GPU machine can lose the machine before
that: the gate's verdicts (``matrices/matrix_gate.json``) and the candidates' ONNX files and manifests
(``candidates/checkpoint_<N>.onnx`` and ``.json``, written by the gate when it took each one) come back,
the candidates' ``.pt`` checkpoints do not. This does what ``finish`` would have done with what came
back: it copies the candidate's ONNX file and manifest to ``throw<mode>.onnx`` / ``.json`` beside them
(the bytes unchanged, so the ONNX SHA-256 is the gate's) and writes the model card
(sim_twin.training.model_card.attach_card) from the gate's state and ``accelerators.json``.

``--iteration N`` cards another pass of the run instead (one that met every bar on every gate seed, not the
one ``finish`` exports: a pass that the paired deploy test over held-out seeds prefers), in place: the card
goes beside ``candidates/checkpoint_<N>.onnx`` and into its manifest, and nothing is copied, so the run's
export stays what ``finish`` chose.

The command and commit are the training command and the commit it ran at (the run's log does not record
them: ``device_runs.sh start`` prints the command); a card that named this checkout's commit would be wrong.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

from sim_twin.training import model_card
from sim_twin.training.matrix_gate import choose_pass, saved_passes


def chosen_pass(gate: dict, first: bool = False, iteration: int | None = None) -> dict:
    """The pass ``finish`` exports (sim_twin.training.matrix_gate.choose_pass: the newest, or where the
    gate compared the passes with the deployed policy the one worse on the fewest cells), or with
    ``first`` the gate state's first pass (``passed``), or the pass at ``iteration``.

    Raises:
        ValueError: no checkpoint met every bar on every gate seed, or the one at ``iteration`` did not."""
    passes = saved_passes(gate)
    if iteration is not None:
        for p in passes:
            if int(p["iteration"]) == iteration:
                return p
        raise ValueError(f"iteration {iteration} did not meet every bar on every gate seed; the passes are at iterations "
                         f"{[int(p['iteration']) for p in passes]}")
    chosen = passes[0] if first and passes else choose_pass(passes)
    if chosen is None:
        raise ValueError("no checkpoint of this run met every bar on every gate seed: nothing to export")
    return chosen


def late_export(run: Path, command: str, commit: str, first: bool = False, iteration: int | None = None) -> Path:
    """Write ``run/throw<mode>.onnx``, its manifest and model card from the gate's chosen pass
    (:func:`chosen_pass`), or with ``iteration`` the card of that pass beside its candidate
    (``candidates/checkpoint_<N>.card.json`` / ``.card.md``, and into its manifest); returns the ONNX path.

    Raises:
        FileNotFoundError: the run has no ``matrices/matrix_gate.json`` or ``config.json``, or the chosen
            candidate's ONNX file or manifest is not under ``run/candidates``.
        ValueError: nothing passed, or not at ``iteration`` (:func:`chosen_pass`), or ``command`` or
            ``commit`` is empty.
        FileExistsError: the run already has an export (the run finished, or this ran before), or with
            ``iteration`` the candidate already has a card."""
    run = Path(run)
    if not command.strip() or not commit.strip():
        raise ValueError("the card needs the training command and the commit it ran at")
    gate = json.loads((run / "matrices" / "matrix_gate.json").read_text())
    cfg = json.loads((run / "config.json").read_text())
    chosen = chosen_pass(gate, first, iteration)
    it = int(chosen["iteration"])
    src = run / "candidates" / Path(chosen["onnx"]).name
    for path in (src, src.with_suffix(".json")):
        if not path.exists():
            raise FileNotFoundError(f"{path}: the candidate of iteration {it} did not come back with the run")
    if iteration is not None:
        out, card = src, model_card.card_paths(src)[0]
        if card.exists():
            raise FileExistsError(f"{card} exists: iteration {it} has its card")
    else:
        out = run / f"throw{gate['mode']}.onnx"
        if out.exists():
            raise FileExistsError(f"{out} exists: the run has an export (move it to candidates/ to replace it)")
        shutil.copyfile(src, out)
        shutil.copyfile(src.with_suffix(".json"), out.with_suffix(".json"))
    acc_path = run / model_card.ACCELERATORS_FILE
    segments = json.loads(acc_path.read_text()) if acc_path.exists() else []
    model_card.attach_card(out, cfg, command, dict(
        iteration=it, gpus=model_card.describe_accelerators(segments, it) if segments else "unknown",
        train_wall_s=chosen["train_wall_s"], verdict_wall_s=chosen.get("verdict_wall_s"),
        world_size=max([s.get("processes", 1) for s in segments] or [1]),
        matrices=[r for r in gate.get("results", []) if r["iteration"] == it], bars_met=True, commit=commit))
    return out


def main(argv: list[str] | None = None) -> int:
    """CLI (module docstring). Returns 0, or 2 with the error on stderr."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", type=Path, help="the run directory (with matrices/matrix_gate.json and candidates/)")
    p.add_argument("--command", required=True, help="the slinger train command of the run (for the card)")
    p.add_argument("--commit", required=True, help="the commit the run trained at (for the card)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--first", action="store_true", help="the first checkpoint that met the bars, not the newest")
    which.add_argument("--iteration", type=int, default=None,
                       help="card this pass in place (candidates/checkpoint_<N>) instead of exporting the chosen one")
    args = p.parse_args(argv)
    try:
        out = late_export(args.run, args.command, args.commit, args.first, args.iteration)
    except (OSError, ValueError) as e:
        print(f"late_export: {e}", file=sys.stderr)
        return 2
    card = json.loads(model_card.card_paths(out)[0].read_text())
    print(f"{out}: iteration {card['iteration']}, ONNX SHA-256 {card['onnx_sha256']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
