#!/bin/sh
# Builds the Go listeners of part (t) offline from Debian's Go sources (GOPATH mode, no module proxy).
#   bench/go_listeners/build.sh [BUILD_DIR]      (default: build/go-listeners at the repository root)
# Needs golang-go, golang-golang-x-net-dev (HTTP/2), golang-google-protobuf-dev, protobuf-compiler
# and protoc-gen-go: only the contract's messages, the listeners speak HTTP/2 themselves
# (connection.go), without grpc-go. The binary is BUILD_DIR/bin/fanout-listeners.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
exec "$root/protos/build_go.sh" "$here" fanout-listeners "${1:-$root/build/go-listeners}"
