#!/usr/bin/env bash
# Builds a profile-guided (PGO) release binary of `tessera`: an instrumented build renders every
# scene under scenes/ at a small size, and LLVM then lays out and inlines the renderer by what those
# renders executed. Same code, same images (a PGO build changes no arithmetic: the comparison at
# the end of this script holds it to that, against target/release built from the same source); the
# renderer's paths/s is what changes (figures in ARCHITECTURE.md, "Choices").
#
#   scripts/build-pgo.sh                # -> target/pgo/tessera
#   TESSERA_PGO_OUT=/path scripts/build-pgo.sh
#
# Needs rustup's llvm-tools component (for llvm-profdata of rustc's own LLVM version; a distribution's
# llvm-profdata of another version cannot read the profiles): installed here if missing.
# Takes two full release builds (about 20 minutes on 2 cores), in target/pgo-gen and target/pgo-use,
# so the ordinary target/release is left alone. docker/build-images.sh uses it when TESSERA_PGO=1.
set -euo pipefail
cd "$(dirname "$0")/.."

out="${TESSERA_PGO_OUT:-target/pgo/tessera}"
# RUSTFLAGS replaces .cargo/config.toml's target rustflags, so they are repeated here.
base_flags="-C target-cpu=x86-64-v3"
host=$(rustc -vV | sed -n 's/^host: //p')
profdata="$(rustc --print sysroot)/lib/rustlib/$host/bin/llvm-profdata"
if [ ! -x "$profdata" ]; then
  rustup component add llvm-tools
fi
data="$PWD/target/pgo-data"
rm -rf "$data" && mkdir -p "$data"

echo "1/3 instrumented build"
RUSTFLAGS="$base_flags -Cprofile-generate=$data" \
  cargo build --release -p tessera-cli --target-dir target/pgo-gen

echo "2/3 training renders"
train=$(mktemp -d)
trap 'rm -rf "$train"' EXIT
while IFS= read -r scene; do
  extra=()
  case "$scene" in
    */envlit/*) extra=(--env scenes/env/sunset.exr) ;;
  esac
  LLVM_PROFILE_FILE="$data/tessera-%p-%m.profraw" target/pgo-gen/release/tessera render "$scene" \
    -o "$train/out.exr" --spp 16 --width 96 --height 72 --threads 2 "${extra[@]}" >/dev/null 2>&1 ||
    echo "  (training render failed, skipped: $scene)"
done < <(find scenes -name '*.gltf' -o -name '*.glb' | sort)
"$profdata" merge -o "$data/merged.profdata" "$data"/*.profraw

echo "3/3 optimised build"
RUSTFLAGS="$base_flags -Cprofile-use=$data/merged.profdata -Cllvm-args=-pgo-warn-missing-function=false" \
  cargo build --release -p tessera-cli --target-dir target/pgo-use

# The PGO binary must render what the ordinary one renders, bit for bit: the ordinary one is brought
# up to date first (a no-op when it is), so the check never compares against another source.
cargo build --release -p tessera-cli
for scene in scenes/cornell/cornell.gltf scenes/glass/glass.gltf scenes/veach/veach.gltf; do
  target/release/tessera render "$scene" -o "$train/a.exr" --spp 4 --width 64 --height 48 >/dev/null 2>&1
  target/pgo-use/release/tessera render "$scene" -o "$train/b.exr" --spp 4 --width 64 --height 48 >/dev/null 2>&1
  cmp -s "$train/a.exr" "$train/b.exr" || { echo "PGO build renders $scene differently: not installed" >&2; exit 1; }
done
mkdir -p "$(dirname "$out")"
cp target/pgo-use/release/tessera "$out"
echo "built $out"
