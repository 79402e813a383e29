#!/usr/bin/env bash
# Builds the `tessera:latest` image on a machine whose Docker engine cannot pull images.
#
#   docker/build-images.sh            # builds the release binary, a base image if needed, then tessera:latest
#   TESSERA_PGO=1 docker/build-images.sh   # the same with a profile-guided binary (scripts/build-pgo.sh:
#                                          # same images; 0.97-1.02 of the plain build's time with today's
#                                          # renderer, see ARCHITECTURE.md; 8-20 more minutes)
#
# Base image, first that works: $TESSERA_BASE_IMAGE if set; debian:bookworm-slim if the engine already has
# it or can pull it; otherwise a minimal Debian bookworm root made here with debootstrap from Debian's
# package archive and imported as `tessera-base:bookworm` (kept, so later builds skip this step).
# The binary is built on the host (same Debian release as the base, so the same glibc).
set -euo pipefail
cd "$(dirname "$0")/.."

if [ "${TESSERA_PGO:-0}" = 1 ]; then
  scripts/build-pgo.sh
  binary=target/pgo/tessera
else
  cargo build --release -p tessera-cli
  binary=target/release/tessera
fi

base="${TESSERA_BASE_IMAGE:-}"
if [ -z "$base" ]; then
  if docker image inspect debian:bookworm-slim >/dev/null 2>&1 || timeout 60 docker pull -q debian:bookworm-slim >/dev/null 2>&1; then
    base=debian:bookworm-slim
  elif docker image inspect tessera-base:bookworm >/dev/null 2>&1; then
    base=tessera-base:bookworm
  else
    echo "no registry reachable: building a Debian bookworm base with debootstrap"
    if ! command -v debootstrap >/dev/null; then
      apt-get update -qq && apt-get install -y -qq debootstrap
    fi
    root=$(mktemp -d)
    mirror="${TESSERA_DEBIAN_MIRROR:-http://deb.debian.org/debian}"
    debootstrap --variant=minbase bookworm "$root" "$mirror" >/dev/null
    # Trim what a container never uses.
    rm -rf "$root"/var/cache/apt/archives/*.deb "$root"/var/lib/apt/lists/* "$root"/usr/share/doc/* "$root"/usr/share/man/*
    tar -C "$root" -c . | docker import - tessera-base:bookworm >/dev/null
    rm -rf "$root"
    base=tessera-base:bookworm
  fi
fi

ctx=target/docker-context
rm -rf "$ctx" && mkdir -p "$ctx"
cp docker/Dockerfile "$ctx/Dockerfile"
cp "$binary" "$ctx/tessera"
# The release profile keeps line tables for profiling; the image does not need them.
if command -v strip >/dev/null; then strip --strip-debug "$ctx/tessera"; fi
docker build -q --build-arg BASE="$base" -t tessera:latest "$ctx" >/dev/null
echo "built tessera:latest on $base"
