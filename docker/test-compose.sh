#!/usr/bin/env bash
# The docker-compose cluster on the real Docker engine (run by .ci/run):
#  1. build the images, `up` with 2 workers, submit the Cornell box from the host with the CLI, and
#     check the EXR equals a local `tessera render` bit for bit;
#  2. with 3 workers, `docker kill` one mid-job and `docker network disconnect` another for longer
#     than its lease before reconnecting it: the job still completes identically;
#  3. restart the coordinator container mid-job: the job completes identically from its checkpoint;
#  then `down -v`. Skips (exit 0, saying so) only where no Docker engine is running.
# Prints "docker: N passed, M failed" last.
set -uo pipefail
cd "$(dirname "$0")/.."

if ! docker info >/dev/null 2>&1; then
  echo "SKIP docker cluster test: no Docker engine is running here"
  echo "docker: 0 passed, 0 failed"
  exit 0
fi
if docker compose version >/dev/null 2>&1; then COMPOSE=(docker compose); else COMPOSE=(docker-compose); fi

bash docker/build-images.sh || { echo "docker: 0 passed, 1 failed (image build)"; exit 1; }

project="tessera-ci-$$"
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
export TESSERA_PORT=$port TESSERA_LEASE_SECONDS=2 TESSERA_TOKEN=ci-token TESSERA_WORKER_SECRET=ci-secret
export TESSERA_COORDINATOR="http://127.0.0.1:$port"
T=target/release/tessera
tmp=$(mktemp -d)
dc() { "${COMPOSE[@]}" -p "$project" -f docker/docker-compose.yml "$@"; }
trap 'dc down -v --remove-orphans >/dev/null 2>&1; rm -rf "$tmp"' EXIT
source docker/lib.sh
workers() { docker ps -q --filter "label=com.docker.compose.project=$project" --filter "label=com.docker.compose.service=worker"; }

# 1. Two workers, bit-identical to a local render.
dc up -d --scale worker=2 >/dev/null 2>&1
if wait_api && id=$($T submit scenes/cornell/cornell.gltf --spp 64 --width 128 --height 128) && wait_done "$id" && same_as_local "$id" 64 two; then
  ok "2 workers: EXR identical to tessera render"
else
  ko "2 workers"; dc logs --tail 30
fi

# 2. Three workers; kill one, cut another off for longer than its lease.
dc up -d --scale worker=3 >/dev/null 2>&1
sleep 2
id=$($T submit scenes/cornell/cornell.gltf --spp 512 --width 128 --height 128)
if wait_units "$id" 6; then
  mapfile -t ws < <(workers)
  docker kill "${ws[0]}" >/dev/null
  net="${project}_default"
  docker network disconnect "$net" "${ws[1]}"
  sleep $((TESSERA_LEASE_SECONDS * 3))
  docker network connect "$net" "${ws[1]}"
  expired=$(curl -s "$TESSERA_COORDINATOR/metrics" 2>/dev/null | awk '/^tessera_leases_expired_total/ {print $2}')
  if wait_done "$id" && same_as_local "$id" 512 chaos; then
    ok "worker killed + worker partitioned ${TESSERA_LEASE_SECONDS}x3 s: identical (leases expired so far: ${expired:-?})"
  else
    ko "worker killed + partitioned"; dc logs --tail 30
  fi
else
  ko "worker killed + partitioned (job did not start)"
fi

# 3. Coordinator restart mid-job.
id=$($T submit scenes/cornell/cornell.gltf --spp 256 --width 128 --height 128 --seed 7)
if wait_units "$id" 6; then
  dc restart coordinator >/dev/null 2>&1
  if wait_api && wait_done "$id" && $T download "$id" -o "$tmp/restart.exr" &&
    $T render scenes/cornell/cornell.gltf --spp 256 --width 128 --height 128 --seed 7 -o "$tmp/restart-local.exr" 2>/dev/null &&
    cmp -s "$tmp/restart.exr" "$tmp/restart-local.exr"; then
    ok "coordinator restarted mid-job: identical"
  else
    ko "coordinator restart"; dc logs --tail 30
  fi
else
  ko "coordinator restart (job did not start)"
fi

dc down -v >/dev/null 2>&1
echo "docker: $passed passed, $failed failed"
[ "$failed" -eq 0 ]
