#!/usr/bin/env bash
# docker/docker-compose.yml deployed as a Docker Swarm stack on this machine's engine (run by .ci/run
# beside the compose test):
#  1. `docker swarm init` a single-node swarm if the engine is not in one (and leave it afterwards);
#  2. `docker stack deploy` the compose file with 2 workers, submit the Cornell box from the host;
#  3. `docker service scale` the workers to 3, submit a longer job, `docker kill` one worker task
#     mid-job (Swarm starts a replacement): the EXR equals a local `tessera render` bit for bit;
#  then `docker stack rm` and the stack's volume removed.
# Skips (exit 0, saying so) only where no Docker engine is running.
# Prints "swarm: N passed, M failed" last.
set -uo pipefail
cd "$(dirname "$0")/.."

if ! docker info >/dev/null 2>&1; then
  echo "SKIP swarm test: no Docker engine is running here"
  echo "swarm: 0 passed, 0 failed"
  exit 0
fi
docker image inspect tessera:latest >/dev/null 2>&1 || bash docker/build-images.sh ||
  { echo "swarm: 0 passed, 1 failed (image build)"; exit 1; }

stack="tessera-ci-$$"
port=$(python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])')
export TESSERA_PORT=$port TESSERA_LEASE_SECONDS=2 TESSERA_TOKEN=ci-token TESSERA_WORKER_SECRET=ci-secret TESSERA_WORKERS=2
export TESSERA_COORDINATOR="http://127.0.0.1:$port"
T=target/release/tessera
tmp=$(mktemp -d)
joined=0
if [ "$(docker info --format '{{.Swarm.LocalNodeState}}')" != active ]; then
  docker swarm init --advertise-addr 127.0.0.1 >/dev/null || { echo "swarm: 0 passed, 1 failed (swarm init)"; exit 1; }
  joined=1
fi
cleanup() {
  docker stack rm "$stack" >/dev/null 2>&1
  # The volume can be removed once the stack's containers are gone.
  for _ in $(seq 1 60); do
    [ -z "$(docker ps -aq --filter "label=com.docker.stack.namespace=$stack")" ] && break
    sleep 1
  done
  docker volume rm "${stack}_tessera-data" >/dev/null 2>&1
  [ "$joined" = 1 ] && docker swarm leave --force >/dev/null 2>&1
  rm -rf "$tmp"
}
trap cleanup EXIT
source docker/lib.sh
wait_workers() { # how many live (not offline) workers
  for _ in $(seq 1 240); do
    n=$(curl -s -H "Authorization: Bearer $TESSERA_TOKEN" "$TESSERA_COORDINATOR/api/v1/workers" |
      python3 -c 'import json,sys; print(sum(w["state"] != "offline" for w in json.load(sys.stdin)["workers"]))' 2>/dev/null) || n=0
    [ "${n:-0}" -ge "$1" ] && return 0
    sleep 0.5
  done
  return 1
}
logs() { docker service logs --tail 20 "${stack}_coordinator" 2>&1 | tail -20; docker service ps "${stack}_worker" 2>&1 | tail -8; }

# 1. The compose file as a stack, two workers.
if ! docker stack deploy -c docker/docker-compose.yml "$stack" >"$tmp/deploy.log" 2>&1; then
  cat "$tmp/deploy.log"
  ko "docker stack deploy"
  echo "swarm: $passed passed, $failed failed"
  exit 1
fi
if wait_api && wait_workers 2 && id=$($T submit scenes/cornell/cornell.gltf --spp 64 --width 128 --height 128) &&
  wait_done "$id" && same_as_local "$id" 64 stack; then
  ok "stack deployed from the compose file, 2 workers: EXR identical to tessera render"
else
  ko "stack with 2 workers"; logs
fi

# 2. Scale to 3 workers; kill one task mid-job.
docker service scale "${stack}_worker=3" >/dev/null 2>&1
if wait_workers 3; then
  ok "docker service scale: 3 workers registered"
else
  ko "scale to 3 workers"; logs
fi
id=$($T submit scenes/cornell/cornell.gltf --spp 512 --width 128 --height 128)
if wait_units "$id" 6; then
  victim=$(docker ps -q --filter "label=com.docker.swarm.service.name=${stack}_worker" | head -1)
  docker kill "$victim" >/dev/null
  if wait_done "$id" && same_as_local "$id" 512 killed; then
    ok "a worker task killed mid-job: identical"
  else
    ko "worker task killed"; logs
  fi
else
  ko "worker task killed (job did not start)"; logs
fi

echo "swarm: $passed passed, $failed failed"
[ "$failed" -eq 0 ]
