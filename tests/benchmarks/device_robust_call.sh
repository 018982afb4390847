#!/bin/bash
# One GPU call of robust fine-tuning (export, train 2D and 3D side by side, site matrix on the CPU cores); docs/training.md.
#
# Layout (copy in before the call, bring back after it): devwork/cfg_{2d,3d}.json (training configs),
# devwork/{2d,3d}/checkpoint.pt and curve.csv (resumed and overwritten), .whl/ (cp312 wheels of what the
# GPU host lacks: mujoco, mujoco-core, mujoco-mjx, rsl-rl-lib, tensordict, trimesh, gitpython, gitdb, smmap,
# pyvers, pydantic, pydantic-core, annotated-types, typing-inspection, mcap, lz4, zstandard,
# eclipse-zenoh, cffi, pycparser). $OUT receives the checkpoints, curves, site matrices and the matrix log.
#
# Steps: export the current checkpoints to ONNX; train 2D and 3D side by side on the GPU (MIN minutes,
# ENVS envs each) while the site matrix of the exported policies runs on the CPU cores (W workers).
# TRAIN=0 runs the matrices only, MATRIX=0 the training only; MODES picks the modes (default "2d 3d"); SEEDS the
# matrix seeds (default 0; seed s > 0 writes site_matrix_<mode>_seed<s>.json: start poses no other seed uses).
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
TAG=${TAG:-f}; MIN=${MIN:-7.0}; ENVS=${ENVS:-16384}; MODES=${MODES:-"2d 3d"}
for m in $MODES; do
python3 - <<PY || exit 1
import json; from pathlib import Path
from sim_twin.training.export import export_checkpoint
cfg = json.loads(Path("devwork/cfg_$m.json").read_text())
export_checkpoint(Path("devwork/$m/checkpoint.pt"), cfg, Path("devwork/throw$m.onnx"), name="throw$m-robust-$TAG")
PY
cp devwork/$m/checkpoint.pt devwork/$m/evaluated.pt
done
if [ "${TRAIN:-1}" = 1 ]; then
for m in $MODES; do
  timeout ${HARD:-540} python3 -m sim_twin.training.train --mode $m --config devwork/cfg_$m.json --num-envs $ENVS \
    --resume devwork/$m/checkpoint.pt --log-dir devwork/$m --max-minutes $MIN > devwork/train_$m.log 2>&1 &
done
fi
if [ "${MATRIX:-1}" = 1 ]; then
for m in $MODES; do for s in ${SEEDS:-0}; do
  f=site_matrix_$m.json; [ "$s" = 0 ] || f=site_matrix_${m}_seed$s.json
  timeout ${MHARD:-300} python3 -m sim_twin.evaluation.cli --policy devwork/throw$m.onnx --matrix --seed $s --workers ${W:-13} --out devwork/$f >> $OUT/matrix.log 2>&1
  cp devwork/$f $OUT/ 2>/dev/null; tail -n 2 $OUT/matrix.log
done; done
fi
wait
for m in $MODES; do
  cp devwork/$m/checkpoint.pt $OUT/ck$m.pt; cp devwork/$m/curve.csv $OUT/curve$m.csv; tail -n 1 devwork/$m/curve.csv
done
grep -i -E "error|Traceback" devwork/train_*.log | head -5
