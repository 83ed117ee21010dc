#!/bin/sh
# Builds the Go listeners of part (t) offline from Debian's Go sources (GOPATH mode, no module proxy),
# as clients/examples/go/build.sh builds propctl.
#   bench/go_listeners/build.sh [BUILD_DIR]      (default: build/go-listeners at the repository root)
# Needs golang-go, golang-golang-x-net-dev (HTTP/2; golang-google-grpc-dev brings it),
# golang-google-protobuf-dev, protobuf-compiler and protoc-gen-go.
# The binary is BUILD_DIR/bin/fanout-listeners; BUILD_DIR/cache is its Go build cache.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
build=$(mkdir -p "${1:-$root/build/go-listeners}" && cd "${1:-$root/build/go-listeners}" && pwd)
proto=propertyservice/v1/property_service.proto
# The import path of the stubs, given here so that the .proto stays free of Go options.
map="M$proto=propertyservice/v1"
mkdir -p "$build/src"
# Only the messages: the listeners speak HTTP/2 themselves (connection.go), without grpc-go's stubs.
protoc -I "$root/protos" --go_out="$build/src" --go_opt="$map" "$root/protos/$proto"
cd "$here"
GO111MODULE=off GOPATH="$build:/usr/share/gocode" GOCACHE="$build/cache" GOFLAGS= \
  go build -o "$build/bin/fanout-listeners" .
