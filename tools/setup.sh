#!/usr/bin/env bash
# Sets up a fresh machine: a virtual environment in .venv with the app and its test tools.
# Needs only Python >= 3.11 and the package registry. Safe to run again (it only adds what is missing).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-}
if [ -z "$PY" ]; then
  for cand in python3.11 python3.12 python3.13 python3; do
    if command -v "$cand" >/dev/null 2>&1 && "$cand" -c 'import sys; sys.exit(sys.version_info < (3, 11))'; then
      PY=$cand; break
    fi
  done
fi
[ -n "$PY" ] || { echo "setup: need Python >= 3.11 (set PYTHON=/path/to/python)" >&2; exit 1; }
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip >/dev/null
.venv/bin/python -m pip install --quiet -e ".[dev,cluster]"
# The live view's browser test (tests/app/test_liveview_browser.py) needs a headless chromium: installed here only
# for tests (CI=true, set by .ci/run, or SETUP_BROWSER=1), from the system's packages; flying never needs it.
if { [ "${CI:-}" = "true" ] || [ "${SETUP_BROWSER:-}" = "1" ]; } \
    && ! command -v chromium >/dev/null 2>&1 && ! command -v chromium-browser >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" = 0 ] || SUDO="sudo -n"
  if command -v apt-get >/dev/null 2>&1 && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get update -qq >/dev/null \
      && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1; then
    echo "setup: chromium installed (for the live view's browser test)" >&2
  else
    echo "setup: could not install chromium (apt-get install chromium): the live view's browser test will fail" >&2
  fi
fi
echo "setup: ready ($(.venv/bin/python --version), companion installed in .venv)" >&2
