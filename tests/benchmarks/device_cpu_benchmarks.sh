#!/bin/bash
# CPU benchmarks on a lent GPU host's 16 cores, in one call (the GPU is not used):
#   cores 2-15: the full blind diagnosis benchmark (sim_twin.diagnosis.cli benchmark, 14 workers);
#   cores 0-1 (a quiet 2-core machine): a simulated machine (plant + runtime, 100 Hz) running, and
#     beside it the preview latency (tests/benchmarks/bench_preview.py, function only) and then the
#     diagnosis speed goals (tests/benchmarks/bench_diagnosis.py, 30 and 300 throws, 2 workers).
# Wheels the host lacks, in .whl/cpu/: mujoco, mujoco-core, mcap, lz4, zstandard, pydantic, pydantic-core,
# annotated-types, typing-inspection, cffi, pycparser, eclipse-zenoh.
# $OUT receives diagnosis_benchmark_all.json, diagnosis_speed.json/.txt, preview.txt and the logs.
# Variables: DEADLINE (s, benchmark stops starting cases after it; 480).
set -u
DEADLINE=${DEADLINE:-480}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/cpu/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1 OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
lscpu | grep -E "Model name|^CPU\(s\)"
taskset -c 2-15 python3 -m sim_twin.diagnosis.cli benchmark --workers 14 --deadline-s $DEADLINE --no-plots \
  --out $OUT/diagnosis_benchmark_all.json > $OUT/benchmark.log 2>&1 &
BENCH=$!
Z=tcp/127.0.0.1:7461
taskset -c 0,1 python3 -m sim_twin.twin.plant --machine-id m1 --listen $Z > $OUT/plant.log 2>&1 &
PLANT=$!
sleep 2
taskset -c 0,1 python3 -m runtime.node --machine-id m1 --connect $Z --policy-2d policies/throw2d.onnx \
  --policy-3d policies/throw3d.onnx --state-dir /tmp/rt > $OUT/runtime.log 2>&1 &
RT=$!
sleep 5
echo "plant alive: $(kill -0 $PLANT 2>/dev/null && echo yes || echo no), runtime alive: $(kill -0 $RT 2>/dev/null && echo yes || echo no)"
taskset -c 0,1 timeout 120 python3 tests/benchmarks/bench_preview.py --no-http --repeats 5 > $OUT/preview.txt 2>&1
echo "preview exit $?"; tail -n 8 $OUT/preview.txt
taskset -c 0,1 timeout $((DEADLINE - 60)) python3 tests/benchmarks/bench_diagnosis.py --case bias --case asym3 --throws 30 --throws 300 \
  --workers 2 --data-dir /tmp/dd --report $OUT/diagnosis_speed.json > $OUT/diagnosis_speed.log 2>&1
echo "diagnosis speed exit $?"; tail -n 12 $OUT/diagnosis_speed.log
echo "plant alive at the end: $(kill -0 $PLANT 2>/dev/null && echo yes || echo no), runtime: $(kill -0 $RT 2>/dev/null && echo yes || echo no)"
kill $PLANT $RT 2>/dev/null
wait $BENCH; echo "benchmark exit $?"; tail -n 5 $OUT/benchmark.log
