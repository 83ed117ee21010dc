#!/usr/bin/env bash
# The whole test suite: install, lint, format check, type check, tests, then the compatibility check
# (tests/compat/check.py: the demo and the unit tests on the other CPythons 3.11-3.13 present, each in
# a venv with the newest dependencies; an interpreter that is absent or an index pip cannot reach is
# a note and a skip).
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e '.[test]'
if [ "$(id -u)" = 0 ]; then SUDO=""; else SUDO="sudo"; fi
# The interop tests drive the example Node.js client; install node and npm if the machine lacks them.
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
  echo "== installing nodejs and npm (Debian packages)"
  $SUDO apt-get update -qq && $SUDO apt-get install -y -qq nodejs npm >/dev/null
fi
# The C device library (services/device/c): its unit tests and the host example need gcc and make,
# the ATmega328P firmware gcc-avr and avr-libc, the simavr run simavr and libsimavr-dev. Install
# what is missing; if that fails, say so: those tests then skip, each with its reason (pytest -ra).
c_missing=""
command -v gcc >/dev/null || c_missing+=" gcc"
command -v make >/dev/null || c_missing+=" make"
command -v avr-gcc >/dev/null || c_missing+=" gcc-avr"
[ -f /usr/lib/avr/include/avr/io.h ] || c_missing+=" avr-libc"
command -v simavr >/dev/null || c_missing+=" simavr"
[ -f /usr/include/simavr/sim_avr.h ] || c_missing+=" libsimavr-dev"
if [ -n "$c_missing" ]; then
  echo "== installing$c_missing (Debian packages, for the C device library)"
  # shellcheck disable=SC2086  # one word per package
  if ! { $SUDO apt-get update -qq && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq $c_missing >/dev/null; }; then
    echo "note: could not install$c_missing; the C device library's tests that need them skip and say why"
  fi
fi
echo "== ruff check"; python -m ruff check .
echo "== ruff format --check"; python -m ruff format --check .
echo "== mypy"; python -m mypy
echo "== pytest"; python -m pytest "$@"
echo "== compatibility check"; python tests/compat/check.py
