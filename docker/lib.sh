# Helpers shared by docker/test-compose.sh and docker/test-swarm.sh (sourced; they expect $T, the
# tessera binary, $tmp, a scratch directory, and TESSERA_COORDINATOR/TESSERA_TOKEN in the environment).
passed=0
failed=0
ok() { echo "PASS $1"; passed=$((passed + 1)); }
ko() { echo "FAIL $1"; failed=$((failed + 1)); }
field() { python3 -c "import json,sys; j=json.load(sys.stdin); print(eval('j' + sys.argv[1]))" "$1"; }
wait_api() {
  for _ in $(seq 1 240); do $T list >/dev/null 2>&1 && return 0; sleep 0.5; done
  return 1
}
wait_units() { # job, minimum units done
  for _ in $(seq 1 600); do
    n=$($T status "$1" 2>/dev/null | field '["progress"]["units_done"]') || n=0
    [ "${n:-0}" -ge "$2" ] && return 0
    sleep 0.1
  done
  return 1
}
wait_done() {
  for _ in $(seq 1 1200); do
    s=$($T status "$1" 2>/dev/null | field '["state"]') || s=""
    [ "$s" = done ] && return 0
    sleep 0.25
  done
  return 1
}
same_as_local() { # job, spp, name: the farm's EXR equals a local render's, byte for byte
  $T download "$1" -o "$tmp/$3.exr" &&
    $T render scenes/cornell/cornell.gltf --spp "$2" --width 128 --height 128 -o "$tmp/$3-local.exr" 2>/dev/null &&
    cmp -s "$tmp/$3.exr" "$tmp/$3-local.exr"
}
