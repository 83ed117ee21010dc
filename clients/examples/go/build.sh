#!/bin/sh
# Builds propctl offline from Debian's Go sources (GOPATH mode: no module proxy is needed).
#   clients/examples/go/build.sh [BUILD_DIR]      (default: build/go at the repository root)
# Needs golang-go, golang-google-grpc-dev, golang-google-protobuf-dev, protobuf-compiler,
# protoc-gen-go and protoc-gen-go-grpc. The binary is BUILD_DIR/bin/propctl.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../.." && pwd)
build=$(mkdir -p "${1:-$root/build/go}" && cd "${1:-$root/build/go}" && pwd)
proto=propertyservice/v1/property_service.proto
# The import path of the stubs, given here so that the .proto stays free of Go options.
map="M$proto=propertyservice/v1"
mkdir -p "$build/src"
protoc -I "$root/protos" \
  --go_out="$build/src" --go_opt="$map" \
  --go-grpc_out="$build/src" --go-grpc_opt="$map" \
  "$root/protos/$proto"
cd "$here"
GO111MODULE=off GOPATH="$build:/usr/share/gocode" GOCACHE="$build/cache" GOFLAGS= \
  go build -o "$build/bin/propctl" .
