#!/bin/bash
# The cp312 wheels a lent GPU machine lacks for `slinger train` and its site-matrix gate, into
# .whl/base/ (keep .whl/ out of git: `echo /.whl/ >> .git/info/exclude`). Carry `.whl/base` in the
# device call and run `bash tests/benchmarks/device_runs.sh install` there.
#
# The versions are this venv's (pip freeze), so the GPU machine trains with what the tests ran.
# mujoco-mjx's wheel carries 12 MB of test models; they are dropped so that the tree and the wheels
# stay under the device call's 64 MiB. Zenoh, MCAP's compressors and MuJoCo Warp are not needed.
set -euo pipefail
cd "$(dirname "$0")/../.."
PKGS="mujoco mujoco-core mujoco-mjx rsl-rl-lib tensordict trimesh GitPython gitdb smmap pyvers pydantic pydantic_core
      annotated-types typing-inspection mcap cffi pycparser absl-py etils"
PIP=${PIP:-.venv/bin/pip}
pins=$($PIP freeze | python3 -c "
import sys
want = {n.lower().replace('_', '-') for n in sys.argv[1:]}
for line in sys.stdin:
    name = line.split('==')[0].strip()
    if '==' in line and name.lower().replace('_', '-') in want:
        print(line.strip())" $PKGS)
mkdir -p .whl/base
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform any -d .whl/base $pins
mjx=$(ls .whl/base/mujoco_mjx-*.whl)
tmp=$(mktemp -d)
(cd "$tmp" && unzip -q "$OLDPWD/$mjx" && rm -rf mujoco/mjx/test_data \
  && for r in *.dist-info/RECORD; do grep -v "mujoco/mjx/test_data" "$r" > "$r.new" && mv "$r.new" "$r"; done \
  && rm "$OLDPWD/$mjx" && zip -q -r -9 "$OLDPWD/$mjx" .)
rm -rf "$tmp"
du -sh .whl/base
