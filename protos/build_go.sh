#!/bin/sh
# Builds a Go program on the contract offline, from Debian's Go sources (GOPATH mode: no module
# proxy is needed, and Debian's Go source packages carry no go.sum a module build could check).
#   protos/build_go.sh PROGRAM_DIR BINARY BUILD_DIR [grpc]
# Generates the contract's messages (protoc-gen-go) into BUILD_DIR/src/propertyservice/v1, and
# grpc-go's stubs beside them (protoc-gen-go-grpc) when the last argument is `grpc`; then builds
# the package in PROGRAM_DIR into BUILD_DIR/bin/BINARY. BUILD_DIR/cache is its Go build cache.
# Used by clients/examples/go/build.sh and bench/go_listeners/build.sh.
set -eu
root=$(cd "$(dirname "$0")/.." && pwd)
program=$(cd "$1" && pwd)
binary=$2
build=$(mkdir -p "$3" && cd "$3" && pwd)
proto=propertyservice/v1/property_service.proto
# The import path of the stubs, given here so that the .proto stays free of Go options.
map="M$proto=propertyservice/v1"
mkdir -p "$build/src"
if [ "${4:-}" = grpc ]; then
  protoc -I "$root/protos" \
    --go_out="$build/src" --go_opt="$map" \
    --go-grpc_out="$build/src" --go-grpc_opt="$map" \
    "$root/protos/$proto"
else
  protoc -I "$root/protos" --go_out="$build/src" --go_opt="$map" "$root/protos/$proto"
fi
cd "$program"
GO111MODULE=off GOPATH="$build:/usr/share/gocode" GOCACHE="$build/cache" GOFLAGS= \
  go build -o "$build/bin/$binary" .
