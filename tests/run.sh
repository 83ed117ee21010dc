#!/usr/bin/env bash
# The whole test suite: install, lint, format check, type check, tests, then the compatibility check
# (tests/compat/check.py: the demo and the unit tests on the other CPythons 3.11-3.13 present, each in
# a venv with the newest dependencies; an interpreter that is absent or an index pip cannot reach is
# a note and a skip).
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e '.[test]'
# The benchmark's peers (the bench extra: asyncua, eclipse-zenoh), for its smoke test. A wheel that cannot
# be had is a printed note, never a failed run: `python -m bench` then says why and skips that peer.
python -m pip install --quiet --disable-pip-version-check --root-user-action=ignore -e '.[bench]' \
  || echo "note: the bench extra (asyncua, eclipse-zenoh) was not installed; the benchmark skips its peers"

# System tools some tests need, from Debian's packages, installed when missing. A failure is a
# printed note, never a failed run: the tests that need the tool then skip, each saying why (-ra).
if [ "$(id -u)" = 0 ]; then SUDO=""; elif command -v sudo >/dev/null; then SUDO="sudo -n"; else SUDO="none"; fi
apt_updated=""
apt_install() {  # apt_install "what it is for" PACKAGE...
  local why="$1"; shift
  echo "== installing $* (Debian packages, for $why)"
  if [ "$SUDO" = none ]; then
    echo "note: not root and no sudo: $* not installed; the tests for $why will skip"
    return 0
  fi
  local log
  # shellcheck disable=SC2086  # SUDO is empty or "sudo -n"
  if ! log=$({ [ -n "$apt_updated" ] || $SUDO apt-get update -qq; } 2>&1 \
      && $SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "$@" 2>&1); then
    echo "note: could not install $*; the tests for $why will skip:"
    echo "$log" | tail -n 5
    return 0
  fi
  apt_updated=1
}
# The interop tests drive the example Node.js client.
if ! command -v node >/dev/null || ! command -v npm >/dev/null; then
  apt_install "the Node.js client" nodejs npm
fi
# The browser tests (tests/browser) drive Debian's Chromium through chromedriver.
if [ ! -x /usr/bin/chromium ] || [ ! -x /usr/bin/chromedriver ]; then
  apt_install "the browser console" chromium chromium-driver
fi
# The C device library (services/device/c): its unit tests and the host example need gcc and make,
# the ATmega328P firmware gcc-avr and avr-libc, the simavr run simavr and libsimavr-dev.
c_missing=()
command -v gcc >/dev/null || c_missing+=(gcc)
command -v make >/dev/null || c_missing+=(make)
command -v avr-gcc >/dev/null || c_missing+=(gcc-avr)
[ -f /usr/lib/avr/include/avr/io.h ] || c_missing+=(avr-libc)
command -v simavr >/dev/null || c_missing+=(simavr)
[ -f /usr/include/simavr/sim_avr.h ] || c_missing+=(libsimavr-dev)
if [ "${#c_missing[@]}" -gt 0 ]; then
  apt_install "the C device library" "${c_missing[@]}"
fi
# Its Cortex-M build (an LM3S6965) needs Debian's bare-metal ARM compiler and newlib (for memcpy and
# the like), and its test runs the firmware in QEMU's lm3s6965evb: ~110 MB to download, ~2.3 GB on
# disk (most of it newlib and libgcc built for every ARM core).
arm_missing=()
command -v arm-none-eabi-gcc >/dev/null || arm_missing+=(gcc-arm-none-eabi)
[ -f /usr/lib/arm-none-eabi/newlib/thumb/v7-m/nofp/libc_nano.a ] || arm_missing+=(libnewlib-arm-none-eabi)
command -v qemu-system-arm >/dev/null || arm_missing+=(qemu-system-arm)
if [ "${#arm_missing[@]}" -gt 0 ]; then
  apt_install "the C device library on Cortex-M" "${arm_missing[@]}"
fi

# The C++ example client (clients/examples/cpp, tests/interop/test_cpp_client.py): CMake, gRPC C++
# and its protoc plugin (~13 MB of packages to download where cmake and g++ are already there).
cpp_missing=()
command -v cmake >/dev/null || cpp_missing+=(cmake)
command -v c++ >/dev/null || cpp_missing+=(g++)
[ -f /usr/include/grpcpp/grpcpp.h ] || cpp_missing+=(libgrpc++-dev)
command -v grpc_cpp_plugin >/dev/null || cpp_missing+=(protobuf-compiler-grpc)
if [ "${#cpp_missing[@]}" -gt 0 ]; then
  apt_install "the C++ client" "${cpp_missing[@]}"
fi
# The Go example client (clients/examples/go, tests/interop/test_go_client.py), built offline from
# Debian's Go sources: the compiler, grpc-go and protobuf-go, and the two protoc plugins
# (~95 MB of packages to download, most of it the Go 1.19 toolchain). golang-google-protobuf-dev and
# protoc-gen-go are the APIv2 protobuf, the only one whose generator knows proto3 `optional`.
go_missing=()
command -v go >/dev/null || go_missing+=(golang-go)
[ -d /usr/share/gocode/src/google.golang.org/grpc ] || go_missing+=(golang-google-grpc-dev)
[ -d /usr/share/gocode/src/google.golang.org/protobuf ] || go_missing+=(golang-google-protobuf-dev)
# grpc-go's codec calls github.com/golang/protobuf: the 1.5 one (APIv2 underneath, registry.go) that
# knows the generated messages, not the 1.3 one apt would pick first for golang-google-grpc-dev.
[ -f /usr/share/gocode/src/github.com/golang/protobuf/proto/registry.go ] \
  || go_missing+=(golang-github-golang-protobuf-1-5-dev)
command -v protoc >/dev/null || go_missing+=(protobuf-compiler)
command -v protoc-gen-go >/dev/null || go_missing+=(protoc-gen-go)
command -v protoc-gen-go-grpc >/dev/null || go_missing+=(protoc-gen-go-grpc)
# The benchmark's Go listeners (bench/go_listeners) speak HTTP/2 with golang.org/x/net's framer
# (golang-google-grpc-dev depends on it; named here so that it is there whatever brought it).
[ -d /usr/share/gocode/src/golang.org/x/net/http2 ] || go_missing+=(golang-golang-x-net-dev)
if [ "${#go_missing[@]}" -gt 0 ]; then
  apt_install "the Go client and listeners" "${go_missing[@]}"
fi
# The container tests (tests/containers) build the gateway's image with podman (runc as its runtime)
# on a base image that mmdebstrap makes here; setup.sh writes why they skip when it cannot.
container_missing=()
command -v podman >/dev/null || container_missing+=(podman)
command -v runc >/dev/null || container_missing+=(runc)
command -v mmdebstrap >/dev/null || container_missing+=(mmdebstrap)
if [ "${#container_missing[@]}" -gt 0 ]; then
  apt_install "the container image" "${container_missing[@]}"
fi
# The shared registry store's tests (tests/integration/test_store_etcd.py and the cluster tests) start
# real etcd servers: Debian's etcd-server (the `etcd` command; ~7 MB). Its service is not needed:
# each test starts its own server on free loopback ports.
if ! command -v etcd >/dev/null; then
  apt_install "the shared registry store (etcd)" etcd-server
fi
# docs/operations.md reads the gateway's JSON log with jq (tests/integration/test_operations_walkthrough.py).
if ! command -v jq >/dev/null; then
  apt_install "the operations page's log queries" jq
fi
bash tests/containers/setup.sh || echo "note: tests/containers/setup.sh failed; the container tests will skip"
# The benchmark's instruction counts (python -m bench.instructions, and its smoke test) run
# the servers under valgrind's callgrind.
if ! command -v valgrind >/dev/null || ! command -v callgrind_control >/dev/null; then
  apt_install "the benchmark's instruction counts" valgrind
fi

echo "== ruff check"; python -m ruff check .
echo "== ruff format --check"; python -m ruff format --check .
echo "== mypy"; python -m mypy
# Two workers side by side (pytest-xdist; PSGATEWAY_TEST_WORKERS=0 runs in this process): each test
# file is one group, so its module fixtures start once (tests/conftest.py).
echo "== pytest"; python -m pytest -n "${PSGATEWAY_TEST_WORKERS:-2}" --dist loadgroup "$@"
echo "== compatibility check"; python tests/compat/check.py
