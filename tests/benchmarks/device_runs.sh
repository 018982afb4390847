#!/bin/bash
# Several `slinger train` runs side by side on one lent GPU machine, detached from the device call so
# that they outlive it (setsid) while the machine is held, with a call that watches them and brings
# their state back. Each run resumes from runs/state/<name>.tar when that is present (a previous
# machine's state: carry `runs/state` in the device call).
#
#   bash tests/benchmarks/device_runs.sh install        # wheels from .whl/base (and .whl/extra if carried)
#   bash tests/benchmarks/device_runs.sh start NAME MODE CONFIG WORKERS [more slinger train args]
#   bash tests/benchmarks/device_runs.sh after PREV NAME MODE CONFIG WORKERS [args]  # `start NAME ...` once the run
#                                                       # PREV has stopped (several runs one after another on
#                                                       # one GPU: set CUDA_VISIBLE_DEVICES for both)
#   bash tests/benchmarks/device_runs.sh watch MINUTES  # progress every minute (ends early once no run trains), then collect
#   bash tests/benchmarks/device_runs.sh collect        # $OUT/<name>.tar per run (gzip), its log as logs/machine1.log.gz
#                                                       # (candidate checkpoints left out but the exported one's and
#                                                       # those its resume state needs), and $OUT/state.tar: every
#                                                       # run's runs/state/<name>.tar (left out when over 16 MiB)
#   bash tests/benchmarks/device_runs.sh state RUN_DIR NAME [DIR]  # runs/state/NAME.tar (or DIR/NAME.tar),
#                                                       # gzip, from RUN_DIR's checkpoint, config, curve, gate
#                                                       # verdicts (and the gate's candidates: under test, passed), GPU record and
#                                                       # machine logs, so that `start NAME` resumes it
#
# After the last call, here: `tar xf <files_at>/<name>.tar` and `python -m tests.benchmarks.keep_run runs/<name>`
# (trims the run to what policies/training keeps) before it moves to policies/training.
#
# To resume on the next machine, here: `tar xf <files_at>/state.tar` (it unpacks runs/state/<name>.tar;
# where it was too large to come back: `tar xf <files_at>/<name>.tar`, then `state runs/<name> <name>`)
# and carry `runs/state` in the call that starts the runs again. Have it ready before the call that
# collects returns: a machine goes back 30 s after a call ends.
#
# The device call sends the whole working tree (64 MiB at most); with the kept training runs it is
# larger: move policies/training out of the tree for the calls (the runs do not read it) and back after.
#
# The copy has no git: export SLINGER_GIT_COMMIT=<commit> in the call that starts a run (the run
# inherits it) so that the model card of an exported policy names the commit it was trained at.
#
# The runs work in a copy of the tree (/tmp/slinger-runs): every device call copies the working tree
# anew, and a file missing for that moment broke a site matrix running from the tree itself.
#
# The GPU is shared by the runs and the CPU cores by their site-matrix gates (WORKERS processes each):
# training wall times measured this way are upper bounds of a run alone on the GPU.
set -u
WORK=${SLINGER_RUNS_WORK:-/tmp/slinger-runs}  # the copy the runs work in (tests set another)
STATE_MAX_BYTES=${SLINGER_STATE_MAX_BYTES:-16777216}  # the largest file a device call brings back (tests set less)
export PYTHONPATH=/tmp/site:$WORK PYTHONUNBUFFERED=1 XLA_PYTHON_CLIENT_PREALLOCATE=false

install() {
  for d in .whl/base .whl/extra; do
    ls $d/*.whl >/dev/null 2>&1 && [ ! -f /tmp/site/.${d#.whl/} ] || continue
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site $d/*.whl || exit 1
    touch /tmp/site/.${d#.whl/}
  done
  mkdir -p $WORK && tar cf - --exclude=./.whl --exclude=./.git . | tar xf - -C $WORK
  nvidia-smi -L
  python3 -c "import mujoco, jax, rsl_rl, torch; print('mujoco', mujoco.__version__, 'jax', jax.__version__, jax.devices(), 'torch', torch.__version__)"
}

start() {
  local name=$1 mode=$2 config=$3 workers=$4; shift 4
  local run=runs/$name resume=""
  [ -f runs/state/$name.tar ] && [ ! -d $run ] && tar xf runs/state/$name.tar  # the whole run or only what resuming needs
  [ -f $run/checkpoint.pt ] && resume="--resume $run/checkpoint.pt"
  mkdir -p $run
  setsid nohup python3 -m sim_twin.training.train --mode $mode --config $config --log-dir $run --gate-workers $workers \
    --max-minutes 600 $resume "$@" >> $run/train.log 2>&1 < /dev/null &
  echo "started $name (pid $!) $resume"
}

after() {
  # A detached waiter: the `[ ]` keeps the pattern from matching the waiter's own command line, and
  # `slinger-after` is what `watch` looks for so that it does not collect between two runs.
  # PREV may itself be queued by an `after` issued just before: that waiter's command line (and `start`'s
  # until it has launched the training) holds `device_runs.sh start PREV`, so this one waits while PREV is
  # queued or training. Queued is asked first: asked second, PREV could start between the two questions.
  local prev=$1; shift
  setsid nohup bash -c "while pgrep -f -- 'device_runs.sh start $prev[ ]' >/dev/null || pgrep -f -- 'log-dir runs/$prev[ ]' >/dev/null; do sleep 5; done
    exec bash tests/benchmarks/device_runs.sh start $(printf '%q ' "$@")" slinger-after >> runs/after.log 2>&1 < /dev/null &
  echo "$1 starts once $prev has stopped (waiter pid $!)"
}

progress() {
  for run in runs/*/; do
    [ -f $run/curve.csv ] || continue
    echo "$(basename $run): $(tail -n 1 $run/curve.csv | cut -d, -f1-9)"
    grep -h "site matrix of" $run/train.log 2>/dev/null | tail -n 2
  done
}

collect() {
  for run in runs/*/; do
    run=${run%/}
    local name=$(basename $run)
    [ "$name" = state ] || [ ! -f $run/train.log ] && continue
    # a checkpoint being written is skipped: wait until it has been still for 3 s
    for _ in $(seq 20); do
      [ $(( $(date +%s) - $(stat -c %Y $run/checkpoint.pt 2>/dev/null || echo 0) )) -ge 3 ] && break; sleep 1
    done
    # the log goes inside the run's tar, where the tree keeps it: a call brings back a limited number of files;
    # a run resumed on another machine keeps the earlier machines' logs (from its state) and adds its own
    mkdir -p $run/logs
    [ -f $run/.machine ] || echo $(( $(ls $run/logs/machine*.log.gz 2>/dev/null | wc -l) + 1 )) > $run/.machine
    gzip -c $run/train.log > $run/logs/machine$(cat $run/.machine).log.gz
    # The candidates' checkpoints stay behind but the exported policy's (which adapting it needs) and those a
    # resume state carries (state_candidates), so that the run's tar alone resumes it (`state` here) where
    # state.tar does not come back. gzip (tar xf reads it): the matrices' per-throw rows compress well.
    local card=$(ls $run/throw*.card.json 2>/dev/null | head -n 1) keep=() c
    [ -n "$card" ] && keep+=("$run/candidates/checkpoint_$(python3 -c "import json, sys; print(json.load(open(sys.argv[1]))['iteration'])" "$card").pt")
    for c in $(state_candidates $run); do keep+=("$run/candidates/$(basename ${c%.onnx}).pt"); done
    local skip=()
    for c in $run/candidates/*.pt; do [ -f "$c" ] && [[ ! " ${keep[*]} " =~ " $c " ]] && skip+=("--exclude=$c"); done
    tar czf $OUT/$name.tar "${skip[@]}" --exclude="$run/train.log" --exclude="$run/.machine" $run
    [ -f $run/checkpoint.pt ] && [ -f $run/config.json ] && state $run $name $WORK/.state/runs/state >/dev/null
  done
  if [ -d $WORK/.state ]; then
    tar cf $OUT/state.tar -C $WORK/.state runs && rm -rf $WORK/.state
    # a device call brings back files of 16 MiB at most: a larger state.tar would be left out; the runs' tars carry it
    [ $(stat -c %s $OUT/state.tar) -le $STATE_MAX_BYTES ] || { rm $OUT/state.tar
      echo "state.tar over $STATE_MAX_BYTES bytes, left out: here, tar xf each run's tar, then bash $0 state runs/NAME NAME"; }
  fi
  ls -la $OUT
}

watch() {
  local end=$(( $(date +%s) + ${1%.*} * 60 ))
  while [ $(date +%s) -lt $end ]; do
    sleep 60; date +%T; progress; nvidia-smi --query-gpu=utilization.gpu,memory.used --format=csv,noheader
    pgrep -f "sim_twin.training.train|slinger-[a]fter" >/dev/null || { echo "no run is training: collecting now"; break; }  # e.g. bars met
  done
  collect
}

state_candidates() {
  # The candidates (ONNX paths as the gate recorded them) that resuming the run in $1 needs: the gate's
  # candidate under test (matrix_gate.json's pending), which it judges again, and the candidates that met
  # the bars, the first (`passed`), the newest (`passes`) and the one a run past the bars exports
  # (matrix_gate.choose_pass: with --gate-compare-with the one worse than the deployed on the fewest cells)
  python3 -c "
import json, sys
sys.path.insert(0, sys.argv[2])
from sim_twin.training.matrix_gate import choose_pass, saved_passes
g = json.load(open(sys.argv[1]))
passes = saved_passes(g)
print(' '.join(sorted({c['onnx'] for c in [g.get('pending'), g.get('passed'), *passes[-1:], choose_pass(passes)] if c})))" \
    "$1/matrices/matrix_gate.json" "$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)" 2>/dev/null
}

state() {
  # What resuming needs and nothing else (TensorBoard events and the other candidates stay behind:
  # the tree and the carried paths of a device call share 64 MiB), under runs/NAME/ as `start` expects.
  local src=${1%/} name=$2 dest=${3:-runs/state} tmp
  [ -f "$src/checkpoint.pt" ] && [ -f "$src/config.json" ] || { echo "state: $src has no checkpoint.pt and config.json" >&2; return 1; }
  tmp=$(mktemp -d)
  mkdir -p "$tmp/runs/$name" "$dest"
  cp "$src/checkpoint.pt" "$src/config.json" "$tmp/runs/$name/"
  for f in curve.csv matrices accelerators.json logs; do [ -e "$src/$f" ] && cp -r "$src/$f" "$tmp/runs/$name/"; done
  # the candidates the resumed run needs (state_candidates), each with its files
  # (sim_twin.training.matrix_gate.CANDIDATE_SUFFIXES: ONNX file, manifest, checkpoint)
  local cand
  for cand in $(state_candidates "$src"); do
    local stem=$src/candidates/$(basename ${cand%.onnx})
    mkdir -p "$tmp/runs/$name/candidates"
    for x in onnx json pt; do
      [ -f "$stem.$x" ] && cp "$stem.$x" "$tmp/runs/$name/candidates/" || echo "state: $stem.$x is not there; the resumed run cannot judge or export it" >&2
    done
  done
  # the gate's plots stay behind: their JSON and tables carry the same figures
  tar cf - -C "$tmp" --exclude="*.png" "runs/$name" | gzip -9 > "$dest/$name.tar"
  rm -rf "$tmp"
  ls -la "$dest/$name.tar"
}

cmd=$1; shift
case $cmd in install|state) ;; *) cd $WORK 2>/dev/null || { echo "run install first"; exit 1; } ;; esac
$cmd "$@"
