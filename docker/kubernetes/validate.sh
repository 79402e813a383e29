#!/usr/bin/env bash
# Validates the Kubernetes manifests against the Kubernetes OpenAPI schemas (kubernetes-validate from
# PyPI carries them; no cluster needed), strictly (unknown fields are errors), and checks that they
# speak the farm's contract: every TESSERA_* variable they set is one the README documents, and the
# autoscaler's metric is one the coordinator exports. A deliberately broken copy must be refused
# (the validator can fail). Run by .ci/run. Prints "kubernetes: N passed, M failed" last.
set -uo pipefail
cd "$(dirname "$0")"
python3 -c 'import kubernetes_validate' 2>/dev/null || pip install -q kubernetes-validate
passed=0
failed=0
ok() { echo "PASS $1"; passed=$((passed + 1)); }
ko() { echo "FAIL $1"; failed=$((failed + 1)); }
manifests=(secret.yaml coordinator.yaml worker.yaml hpa.yaml prometheus-adapter-rules.yaml)
for v in 1.30.0 1.37.0; do
  if kubernetes-validate --strict --quiet -k "$v" "${manifests[@]}"; then
    ok "manifests valid against Kubernetes $v (strict)"
  else
    ko "manifests against Kubernetes $v"
  fi
done
for m in "${manifests[@]}"; do
  grep -q "^  - $m$" kustomization.yaml || ko "kustomization.yaml does not list $m"
done
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
sed 's/replicas: 2/replicas: two/' worker.yaml > "$tmp/broken.yaml"
if kubernetes-validate --strict --quiet "$tmp/broken.yaml" >/dev/null 2>&1; then
  ko "a broken manifest (replicas: two) passed the validator"
else
  ok "a broken manifest is refused"
fi
unknown=""
for var in $(grep -ho 'TESSERA_[A-Z_]*' coordinator.yaml worker.yaml | sort -u); do
  grep -q "$var" ../../README.md || unknown="$unknown $var"
done
if [ -z "$unknown" ]; then ok "every TESSERA_* variable set is documented"; else ko "undocumented variables:$unknown"; fi
metric=$(sed -nE 's/^ *name: (tessera_[a-z_]+)$/\1/p' hpa.yaml | head -1)
if [ -n "$metric" ] && grep -q "$metric " ../../coordinator/src/rest.rs; then
  ok "the autoscaler's metric $metric is exported by the coordinator"
else
  ko "the autoscaler's metric '$metric' is not exported"
fi
echo "kubernetes: $passed passed, $failed failed"
[ "$failed" -eq 0 ]
