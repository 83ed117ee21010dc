#!/bin/sh
# Builds propctl offline from Debian's Go sources (GOPATH mode: no module proxy is needed).
#   clients/examples/go/build.sh [BUILD_DIR]      (default: build/go at the repository root)
# Needs golang-go, golang-google-grpc-dev, golang-google-protobuf-dev, protobuf-compiler,
# protoc-gen-go and protoc-gen-go-grpc. The binary is BUILD_DIR/bin/propctl.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
exec "$root/protos/build_go.sh" "$here" propctl "${1:-$root/build/go}" grpc
