#!/bin/bash
# One GPU call of `slinger train` with its site-matrix gate on the CPU cores beside it, from scratch
# or resumed from the state a previous call brought back.
#
# Layout (copy in before the call): .whl/base/ (cp312 wheels the GPU host lacks: mujoco, mujoco-core,
# mujoco-mjx, rsl-rl-lib, tensordict, trimesh, gitpython, gitdb, smmap, pyvers, pydantic, pydantic-core,
# annotated-types, typing-inspection, mcap, lz4, zstandard, cffi, pycparser; eclipse-zenoh there or in .whl/extra/), optionally
# runs/state/<name>.tar (the previous call's run directory). $OUT receives <name>.tar (checkpoints, curve,
# TensorBoard events, gate state, every matrix) and the training log.
#
# Variables: MODE (2d), NAME (run name, default scratch<mode>), MIN (training minutes, 7), WAIT (minutes
# to wait for a running matrix at the end, 1.3), GPUS (1), EXTRA (more `slinger train` arguments).
set -u
MODE=${MODE:-2d}; NAME=${NAME:-scratch$MODE}; MIN=${MIN:-7}; WAIT=${WAIT:-1.3}; GPUS=${GPUS:-1}
[ -d /tmp/site/mujoco ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/base/*.whl || exit 1
# eclipse-zenoh (the matrix's runtime modules import it) may travel apart, for the 64 MiB limit of a call
[ -d /tmp/site/zenoh ] || python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --target /tmp/site .whl/*/eclipse_zenoh*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false
RUN=runs/$NAME
[ -f runs/state/$NAME.tar ] && tar xf runs/state/$NAME.tar
RESUME=""; [ -f $RUN/checkpoint.pt ] && RESUME="--resume $RUN/checkpoint.pt"
nvidia-smi -L
timeout ${HARD:-570} python3 -m sim_twin.training.train --mode $MODE --log-dir $RUN --max-minutes $MIN --gate-wait-minutes $WAIT \
  --gpus $GPUS $RESUME ${EXTRA:-} > $OUT/train_$NAME.log 2>&1
echo "train exit $?"
tar cf $OUT/$NAME.tar --exclude="$RUN/candidates/*.pt" $RUN  # candidate checkpoints stay on the host (size)
grep -E "site matrix of|training stopped|Traceback|Error" $OUT/train_$NAME.log | tail -n 20
tail -n 3 $RUN/curve.csv | cut -c1-200
