#!/usr/bin/env bash
# The whole test suite: install, lint, format check, type check, tests, then the compatibility check
# (tests/compat/check.py: the demo and the unit tests on the other CPythons 3.11-3.13 present, each in
# a venv with the newest dependencies; an interpreter that is absent or an index pip cannot reach is
# a note and a skip).
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e '.[test]'
# The interop tests drive the example Node.js client; install node and npm if the machine lacks them.
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
  echo "== installing nodejs and npm (Debian packages)"
  if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq nodejs npm >/dev/null
fi
# The browser tests (tests/browser) drive Debian's Chromium through chromedriver; install both if
# missing. A failure is a note: those tests then skip, saying why.
if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then
  echo "== installing chromium and chromium-driver (Debian packages)"
  if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo -n"; else SUDO="none"; fi
  if [ "$SUDO" = none ]; then
    echo "note: not root and no sudo: chromium and chromium-driver not installed; the browser tests will skip"
  elif ! apt_log=$({ $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver; } 2>&1); then
    echo "note: could not install chromium and chromium-driver; the browser tests will skip:"
    echo "$apt_log" | tail -n 5
  fi
fi
echo "== ruff check"; python -m ruff check .
echo "== ruff format --check"; python -m ruff format --check .
echo "== mypy"; python -m mypy
echo "== pytest"; python -m pytest "$@"
echo "== compatibility check"; python tests/compat/check.py
