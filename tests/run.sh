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
echo "== ruff check"; python -m ruff check .
echo "== ruff format --check"; python -m ruff format --check .
echo "== mypy"; python -m mypy
echo "== pytest"; python -m pytest "$@"
echo "== compatibility check"; python tests/compat/check.py
