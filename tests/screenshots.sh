#!/usr/bin/env bash
# Photograph every console page at 1440x900, 1024x768 and 390x844 into reports/screenshots/
# (docs/operator-guide.md links the set). The same browser tests that check the layout bars take them.
set -euo pipefail
cd "$(dirname "$0")/.."
mkdir -p reports/screenshots
export SLINGER_SCREENSHOTS="$PWD/reports/screenshots" MUJOCO_GL=egl
python -m pytest -q tests/test_browser_pages.py tests/test_browser_console.py \
  -k "accessible or layout or throw_from_a_click or return_to_ready" "$@"
# The operator guide's pictures (docs/operator-guide.md): status strip, alarm, E-STOP reset.
mkdir -p docs/img
SLINGER_SCREENSHOTS="$PWD/docs/img" python -m pytest -q tests/test_browser_operator.py "$@"
