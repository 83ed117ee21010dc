#!/usr/bin/env bash
# Builds the gateway's image with podman for the container tests (tests/containers), once per run,
# reusing cached layers. Never fails the test command: when podman is missing or cannot run a
# container here, it writes the reason to build/containers/status and the container tests skip,
# printing it.
#
# What podman needs on this kind of machine (a VM, root, cgroups v1, no systemd, no registry):
# * runtime runc, cgroup manager cgroupfs, events in a file (no journald, no systemd);
# * explicit nofile/nproc ulimits: podman's default nofile (1048576) is above the hard limit that
#   the machine gives root, and runc then fails with "error setting rlimits ... operation not
#   permitted"; the values come from `ulimit -Hn` / `ulimit -Hu`, capped;
# * a base image made here: mmdebstrap a minimal Debian with python3 and `podman import` it as
#   localhost/psgateway-base:bookworm (kept between runs). A machine that can pull passes its own
#   base: PYTHON_IMAGE=docker.io/library/python:3.11-slim-bookworm tests/containers/setup.sh;
# * the host's CA bundle mounted into the build, for pip behind a TLS-inspecting proxy.
# These settings live in build/containers/containers.conf (CONTAINERS_CONF), not in /etc.
set -uo pipefail
cd "$(dirname "$0")/../.."
out=build/containers
mkdir -p "$out"
status="$out/status"
image="${PSGATEWAY_TEST_IMAGE:-localhost/psgateway:test}"
base_tag=localhost/psgateway-base:bookworm
log="$out/setup.log"
: >"$log"
# Until the build has finished, the tests skip: an image of an older tree is never tested.
printf 'skip: tests/containers/setup.sh did not finish (see %s)\n' "$log" >"$status"
etcd_status="$out/etcd-status"
printf 'skip: tests/containers/setup.sh did not finish (see %s)\n' "$log" >"$etcd_status"

skip() {  # skip "why": the tests skip with this reason
  echo "note: container tests will skip: $1"
  printf 'skip: %s\n' "$1" >"$status"
  exit 0
}

command -v podman >/dev/null || skip "podman is not installed (Debian package podman, with runc)"

cap() { local v; v=$(ulimit -H "$1"); [ "$v" = unlimited ] && v=$2; [ "$v" -gt "$2" ] && v=$2; echo "$v"; }
nofile=$(cap -n 65536)
nproc=$(cap -u 8192)
cat >"$out/containers.conf" <<CONF
# Written by tests/containers/setup.sh; used through CONTAINERS_CONF.
[containers]
default_ulimits = ["nofile=$nofile:$nofile", "nproc=$nproc:$nproc"]
[engine]
cgroup_manager = "cgroupfs"
events_logger = "file"
runtime = "runc"
CONF
export CONTAINERS_CONF="$PWD/$out/containers.conf"

if [ -z "${PYTHON_IMAGE:-}" ]; then
  PYTHON_IMAGE=$base_tag
  if ! podman image exists "$base_tag"; then
    command -v mmdebstrap >/dev/null || skip "no base image and no mmdebstrap to make one (Debian package mmdebstrap)"
    echo "== making the base image $base_tag (mmdebstrap: Debian bookworm, python3)"
    tar="$out/base.tar"
    # Docs, manuals and translations are left out, as the official slim images do.
    if ! mmdebstrap --quiet --mode=root --variant=minbase \
        --include=python3,python3-venv,ca-certificates \
        --aptopt='Apt::Install-Recommends "false"' \
        --dpkgopt='path-exclude=/usr/share/man/*' --dpkgopt='path-exclude=/usr/share/doc/*' \
        --dpkgopt='path-include=/usr/share/doc/*/copyright' \
        --dpkgopt='path-exclude=/usr/share/locale/*' --dpkgopt='path-exclude=/usr/share/info/*' \
        bookworm "$tar" >>"$log" 2>&1; then
      tail -n 5 "$log"; rm -f "$tar"; skip "mmdebstrap could not make the base image (see $log)"
    fi
    if ! podman import --change 'CMD ["python3"]' "$tar" "$base_tag" >>"$log" 2>&1; then
      tail -n 5 "$log"; rm -f "$tar"; skip "podman import of the base image failed (see $log)"
    fi
    rm -f "$tar"
  fi
fi

# Can podman start a container at all here? The error says why not.
if ! probe=$(podman run --rm --network none "$PYTHON_IMAGE" python3 -c 'print("ok")' 2>&1); then
  skip "podman cannot run a container here: $(echo "$probe" | tail -n 1)"
fi

echo "== building $image (podman build, base $PYTHON_IMAGE)"
ca=()
for bundle in "${SSL_CERT_FILE:-}" /etc/ssl/certs/ca-certificates.crt; do
  if [ -n "$bundle" ] && [ -f "$bundle" ]; then
    ca=(--volume "$(realpath "$bundle"):/etc/ssl/certs/ca-certificates.crt:ro"); break
  fi
done
start=$(date +%s)
# The first two stages are tagged too (IMAGE-build, IMAGE-install): their layers are the cache of
# the next run, and an untagged stage is what `podman image prune` removes below.
for target in build install ""; do
  tag="$image${target:+-$target}"
  if ! podman build --format docker --layers "${ca[@]}" --build-arg "PYTHON_IMAGE=$PYTHON_IMAGE" \
      ${target:+--target "$target"} --tag "$tag" . >>"$log" 2>&1; then
    tail -n 15 "$log"; skip "podman build failed (see $log)"
  fi
done
size=$(podman image inspect --format '{{.Size}}' "$image")
echo "built $image in $(( $(date +%s) - start )) s: $(( size / 1000000 )) MB"
# The layers of earlier builds, no longer under any tag: the cache does not grow without bound.
podman image prune --force >>"$log" 2>&1 || true
printf 'ready: %s\n' "$image" >"$status"

# The compose cluster's etcd (tests/containers/test_compose_cluster.py): the image ETCD_IMAGE
# names (a machine that can pull: ETCD_IMAGE=gcr.io/etcd-development/etcd:v3.5.17), or else the
# host's etcd (Debian's etcd-server: linked against glibc alone) copied onto the same base.
if [ -n "${ETCD_IMAGE:-}" ]; then
  printf 'ready: %s\n' "$ETCD_IMAGE" >"$etcd_status"
elif etcd_bin=$(command -v etcd); then
  etcd_image=localhost/psgateway-etcd:test
  context="$out/etcd-image"
  mkdir -p "$context"
  cp "$etcd_bin" "$context/etcd"
  printf 'FROM %s\nCOPY etcd /usr/local/bin/etcd\n' "$PYTHON_IMAGE" >"$context/Containerfile"
  if podman build --format docker --tag "$etcd_image" "$context" >>"$log" 2>&1; then
    printf 'ready: %s\n' "$etcd_image" >"$etcd_status"
  else
    printf 'skip: podman build of the etcd image failed (see %s)\n' "$log" >"$etcd_status"
  fi
else
  printf 'skip: no etcd image: set ETCD_IMAGE to one, or install etcd (Debian package etcd-server)\n' \
    >"$etcd_status"
fi
