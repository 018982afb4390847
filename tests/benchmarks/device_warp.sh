#!/bin/bash
# warp-lang for a lent GPU machine, whose image has none (MJX-Warp and bare MuJoCo Warp rows of the
# throughput benchmark need it; training does not). Its wheel (149 MB) exceeds what one device call
# carries beside the tree (64 MiB), so it travels in parts over consecutive calls to one warm machine:
#
#   here, once:   bash tests/benchmarks/device_warp.sh parts      # .whl/warp1 .. .whl/warp3 (keep .whl/ out of git)
#   call 1:       carry .whl/base and .whl/warp1: bash tests/benchmarks/device_runs.sh install && bash tests/benchmarks/device_warp.sh put .whl/warp1
#   call 2, 3:    carry .whl/warp2 (then .whl/warp3):             bash tests/benchmarks/device_warp.sh put .whl/warp2
#
# Each `put` adds its part to /tmp/warp-parts; once every part is there (their SHA-256 against the one
# `parts` recorded) it unpacks warp into /tmp/site, where device_runs.sh's PYTHONPATH looks. Send each
# call within 30 s of the last one's end, or the machine goes back with the parts.
#
# The wheel is this venv's warp-lang version, without warp-clang.so (CPU kernels only) and its
# examples and tests, as an xz-compressed tar (79 MB for 1.19.0) cut into parts of at most
# PART_BYTES (the first smaller, as it travels with .whl/base).
set -euo pipefail
cd "$(dirname "$0")/../.."
FIRST_BYTES=15000000
PART_BYTES=38000000

parts() {
  local ver tmp tarball
  ver=$(.venv/bin/pip show warp-lang 2>/dev/null | sed -n 's/^Version: //p')
  [ -n "$ver" ] || { echo "warp-lang is not in .venv: pip install warp-lang first" >&2; exit 1; }
  tmp=$(mktemp -d)
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 -d "$tmp" "warp-lang==$ver"
  mkdir "$tmp/x" && (cd "$tmp/x" && unzip -q ../warp_lang-*.whl && rm -rf warp/examples warp/tests warp/bin/warp-clang.so)
  tarball="$tmp/warp.tar.xz"
  tar cf - -C "$tmp/x" . | xz -T2 -9 > "$tarball"
  rm -rf .whl/warp[0-9]*
  mkdir -p .whl/warp1 && head -c $FIRST_BYTES "$tarball" > .whl/warp1/part
  tail -c +$((FIRST_BYTES + 1)) "$tarball" > "$tmp/rest"
  split -b $PART_BYTES -d -a 1 "$tmp/rest" "$tmp/rest."
  local i=2 f
  for f in "$tmp"/rest.[0-9]; do
    mkdir -p .whl/warp$i && mv "$f" .whl/warp$i/part
    i=$((i + 1))
  done
  local n=$((i - 1)) sha
  sha=$(sha256sum "$tarball" | cut -d' ' -f1)
  for d in .whl/warp[0-9]*; do echo "$n $sha" > "$d/whole"; done
  rm -rf "$tmp"
  ls -la .whl/warp*/part
}

put() {
  local dir=${1%/} n sha
  read -r n sha < "$dir/whole"
  mkdir -p /tmp/warp-parts /tmp/site
  cp "$dir/part" "/tmp/warp-parts/${dir##*warp}"
  local have
  have=$(ls /tmp/warp-parts | wc -l)
  echo "warp part ${dir##*warp} of $n here ($have in all)"
  [ "$have" -eq "$n" ] || return 0
  local got
  got=$(for i in $(seq "$n"); do cat /tmp/warp-parts/$i; done | sha256sum | cut -d' ' -f1)
  [ "$got" = "$sha" ] || { echo "warp parts do not add up (SHA-256 $got, expected $sha)" >&2; exit 1; }
  for i in $(seq "$n"); do cat /tmp/warp-parts/$i; done | tar xJf - -C /tmp/site
  rm -rf /tmp/warp-parts
  PYTHONPATH=/tmp/site python3 -c "import warp; warp.init(); print('warp', warp.__version__, warp.get_cuda_devices())"
}

cmd=${1:?usage: device_warp.sh parts or put DIR}; shift
$cmd "$@"
