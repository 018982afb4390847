"""Average the weights of a run's late gate candidates (ONNX), to test whether the landing bias that moves
from checkpoint to checkpoint averages out.

``python -m tests.benchmarks.checkpoint_average OUT.onnx CANDIDATE.onnx [CANDIDATE.onnx ...] [--name NAME]``

Late in a `slinger train --no-stop-at-bars` run the adaptive learning rate stays at 2-9e-4 (rsl_rl's
``desired_kl`` 0.01; TensorBoard ``Loss/learning_rate``) and a cell's landing bias moves by a few
centimetres between checkpoints 100-200 iterations apart (throw2d-scratch-n1's nominal 10 m: +0.058,
+0.081, +0.068 m at iterations 1925, 2450, 3075, seeds 0-1). Averaging the weights of checkpoints
from one run (stochastic weight averaging, Izmailov et al. 2018, "Averaging Weights Leads to Wider
Optima and Better Generalization", arXiv:1803.05407) removes the part of that motion that is noise
around a common solution. The ONNX files are the gate's exports of one network (sim_twin.training.export:
observation normaliser, three Gemm layers); every initializer, the normaliser's mean and scale
included, is averaged element-wise with equal weights. The manifest is the newest candidate's with the
name and the ONNX SHA-256 replaced and ``training.averaged_from`` listing the inputs.

Raises SystemExit with a message when the candidates' graphs differ (names, shapes or operators).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from runtime.policy import sha256_of, write_manifest


def average(paths: list[Path]) -> onnx.ModelProto:
    """The first model with each initializer replaced by the mean over ``paths`` (float32).

    Raises:
        ValueError: fewer than two models, or graphs that differ in operators, initializer names or shapes."""
    if len(paths) < 2:
        raise ValueError("averaging needs at least two candidates")
    models = [onnx.load(str(p)) for p in paths]
    ops = [[n.op_type for n in m.graph.node] for m in models]
    if any(o != ops[0] for o in ops):
        raise ValueError("the candidates' graphs differ in their operators")
    out = models[0]
    arrays = [{i.name: numpy_helper.to_array(i) for i in m.graph.initializer} for m in models]
    for init in out.graph.initializer:
        if any(init.name not in a or a[init.name].shape != arrays[0][init.name].shape for a in arrays):
            raise ValueError(f"initializer {init.name}: the candidates differ (missing or of another shape in one)")
        stack = [a[init.name] for a in arrays]
        init.CopyFrom(numpy_helper.from_array(np.mean(np.stack(stack), axis=0).astype(stack[0].dtype), init.name))
    return out


def main(argv: list[str] | None = None) -> int:
    """CLI (module docstring); returns 0, or 2 with a message on stderr."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("out", type=Path)
    p.add_argument("candidates", type=Path, nargs="+")
    p.add_argument("--name", help="the manifest's name (default: the output file's stem)")
    args = p.parse_args(argv)
    try:
        model = average(args.candidates)
    except (OSError, ValueError) as e:
        print(f"checkpoint_average: {e}", file=sys.stderr)
        return 2
    args.out.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(args.out))
    manifest = json.loads(args.candidates[-1].with_suffix(".json").read_text())
    manifest["name"] = args.name or args.out.stem
    manifest["onnx_sha256"] = sha256_of(args.out)
    manifest.setdefault("training", {})["averaged_from"] = [str(c) for c in args.candidates]
    manifest["training"].pop("model_card", None)
    write_manifest(args.out, manifest)
    print(f"{args.out}: mean of {len(args.candidates)} candidates, ONNX SHA-256 {manifest['onnx_sha256']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
