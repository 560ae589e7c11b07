#!/usr/bin/env bash
# Prepares, on this machine (Debian 12, with its package registry), everything the GPU
# check (tools/scripts/gpu-check.sh, docs/REAL_GPU.md) needs on a machine that has a GPU but no
# Rust toolchain, package registry or network: one ignored folder, .gpu-check/, carried
# there beside the working tree.
#
#   .gpu-check/bin/          flythrough, citystream and the bind_cost bench, release builds
#                            (stripped, or bin.tar.xz instead, when that is what fits)
#   .gpu-check/debs/loader/  libvulkan1 and the GL dispatch libraries NVIDIA's driver loads
#   .gpu-check/debs/layers/  vulkan-validationlayers (unpacked there into scratch, never /)
#   .gpu-check/debs/tools/   vulkan-tools and its libraries (vulkaninfo: the driver version)
#   .gpu-check/PACK_INFO     commit, toolchain, sizes and checksums
#
# The working tree and the carried folder together must stay under 64 MiB. At the end it
# prints the folder's size and the `carry` list and command for the device machine.
#
# Environment:
#   GPU_CHECK_PACK           the folder (default .gpu-check)
#   GPU_CHECK_PACK_BUILD     1 (default): build the binaries first; 0: take what is built
#   GPU_CHECK_PACK_FROM      take flythrough, citystream and bind_cost from this folder
#                            instead of target/ (no build)
#   GPU_CHECK_PACK_REFRESH   1: download the packages again even where they are there
#   CARGO, CARGO_TARGET_DIR  as for cargo
set -euo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/../.."

PACK=${GPU_CHECK_PACK:-.gpu-check}
BUILD=${GPU_CHECK_PACK_BUILD:-1}
FROM=${GPU_CHECK_PACK_FROM:-}
REFRESH=${GPU_CHECK_PACK_REFRESH:-0}
CARGO=${CARGO:-cargo}
TARGET=${CARGO_TARGET_DIR:-target}
LIMIT=$((64 << 20))
# Kept free under the limit: the tree grows between packing and running.
MARGIN=$((2 << 20))

LOADER_DEBS=(libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
LAYER_DEBS=(vulkan-validationlayers)
TOOL_DEBS=(vulkan-tools libwayland-client0 libffi8 libx11-6 libxcb1 libxau6 libxdmcp6 libbsd0 libmd0)

say() { printf '[gpu-check-pack] %s\n' "$*"; }
fail() {
    printf '[gpu-check-pack] ERROR: %s\n' "$*" >&2
    exit 1
}
mib() { awk -v b="$1" 'BEGIN { printf "%.1f MiB", b / 1048576 }'; }

case $PACK in "" | / | . | ..) fail "GPU_CHECK_PACK=$PACK is not a folder of its own" ;; esac
git check-ignore -q "$PACK/bin" || fail "$PACK is not ignored by git (add /$PACK/ to .gitignore): it must travel as a carried path"

# --- binaries -------------------------------------------------------------------------
if [[ -n $FROM ]]; then
    fly=$FROM/flythrough cs=$FROM/citystream bind=$FROM/bind_cost
    say "binaries from $FROM"
else
    bench_log=$(mktemp)
    trap 'rm -f "$bench_log"' EXIT
    if [[ $BUILD == 1 ]]; then
        say "building the release binaries: $CARGO build --release --workspace --bins"
        "$CARGO" build --release --workspace --bins
        say "building the bind_cost bench: $CARGO bench -p citystream-engine --bench bind_cost --no-run"
        "$CARGO" bench -p citystream-engine --bench bind_cost --no-run 2>&1 | tee "$bench_log"
    fi
    fly=$TARGET/release/flythrough cs=$TARGET/release/citystream
    # cargo names the bench's executable: "Executable benches/bind_cost.rs (target/release/deps/bind_cost-HASH)".
    bind=$(sed -nE 's/.*Executable .*\((.*bind_cost-[0-9a-f]+)\).*/\1/p' "$bench_log" | tail -n1)
    if [[ -z $bind ]]; then
        bind=$(find "$TARGET/release/deps" -maxdepth 1 -type f -name 'bind_cost-*' ! -name '*.*' -perm -u+x \
            -printf '%T@ %p\n' 2>/dev/null | sort -rn | head -n1 | cut -d' ' -f2-)
    fi
fi
for b in "$fly" "$cs" "$bind"; do
    [[ -n $b && -x $b ]] || fail "no binary ${b:-bind_cost}: run without GPU_CHECK_PACK_BUILD=0, or build with \`cargo build --release --workspace --bins\` and \`cargo bench -p citystream-engine --bench bind_cost --no-run\`"
done

rm -rf "${PACK:?}/bin" "${PACK:?}"/bin.tar.*
mkdir -p "$PACK/bin"
cp "$fly" "$PACK/bin/flythrough"
cp "$cs" "$PACK/bin/citystream"
cp "$bind" "$PACK/bin/bind_cost"
chmod 755 "$PACK/bin/"*

# --- packages ---------------------------------------------------------------------------
# amd64 packages whatever this machine is (the device machine is x86-64).
APT=(apt-get)
if [[ $(dpkg --print-architecture) != amd64 ]]; then
    mkdir -p /tmp/amd64/partial
    APT=(apt-get -oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    say "this machine is $(dpkg --print-architecture): amd64 package lists in /tmp/amd64"
    "${APT[@]}" update -q
fi
download() { # download FOLDER PACKAGE...
    local dir=$1
    shift
    local have
    have=$(find "$dir" -maxdepth 1 -name '*.deb' 2>/dev/null | wc -l)
    if [[ $REFRESH != 1 ]] && ((have >= $#)); then
        say "$dir: $have packages already there (GPU_CHECK_PACK_REFRESH=1 downloads them again)"
        return 0
    fi
    rm -rf "$dir"
    mkdir -p "$dir"
    say "downloading into $dir: $*"
    if ! (cd "$dir" && "${APT[@]}" download -q "$@"); then
        say "download failed; apt-get update, then once more"
        "${APT[@]}" update -q
        (cd "$dir" && "${APT[@]}" download -q "$@") || fail "could not download $* (apt-get download)"
    fi
}
download "$PACK/debs/loader" "${LOADER_DEBS[@]}"
download "$PACK/debs/layers" "${LAYER_DEBS[@]}"
download "$PACK/debs/tools" "${TOOL_DEBS[@]}"

# --- size ---------------------------------------------------------------------------------
# What travels besides the carried folder: tracked files and untracked ones git does not ignore.
tree_bytes() {
    git ls-files -z --cached --others --exclude-standard |
        xargs -0 -r stat -c %s 2>/dev/null | awk '{ s += $1 } END { printf "%d", s }'
}
pack_bytes() { du -sb "$PACK" | cut -f1; }
TREE=$(tree_bytes)
total=$((TREE + $(pack_bytes)))
if ((total > LIMIT - MARGIN)); then
    say "tree $(mib "$TREE") + $PACK $(mib "$(pack_bytes)") is over $(mib $((LIMIT - MARGIN))): stripping debug info"
    strip --strip-debug "$PACK"/bin/*
    total=$((TREE + $(pack_bytes)))
fi
if ((total > LIMIT - MARGIN)); then
    say "still $(mib "$total"): stripping every symbol"
    strip --strip-all "$PACK"/bin/*
    total=$((TREE + $(pack_bytes)))
fi
if ((total > LIMIT - MARGIN)); then
    say "still $(mib "$total"): compressing the binaries (gpu-check.sh unpacks them into scratch)"
    if command -v xz >/dev/null; then
        tar -cJf "$PACK/bin.tar.xz" -C "$PACK/bin" .
    else
        tar -czf "$PACK/bin.tar.gz" -C "$PACK/bin" .
    fi
    rm -rf "${PACK:?}/bin"
    total=$((TREE + $(pack_bytes)))
fi
((total <= LIMIT)) || fail "the tree ($(mib "$TREE")) and $PACK ($(mib "$(pack_bytes)")) come to $(mib "$total"), over the 64 MiB that may travel"

# --- what was packed ------------------------------------------------------------------------
{
    printf 'packed %s on %s\n' "$(date -u +%Y-%m-%dT%H:%M:%SZ)" "$(uname -n)"
    printf 'commit %s%s\n' "$(git rev-parse --short=12 HEAD 2>/dev/null || echo unknown)" \
        "$([[ -n $(git status --porcelain --untracked-files=no 2>/dev/null) ]] && echo ' (with uncommitted changes)')"
    printf 'toolchain %s\n' "$(rustc -V 2>/dev/null || echo unknown)"
    for f in "$PACK"/bin/* "$PACK"/bin.tar.*; do
        [[ -e $f ]] || continue
        printf '%s %s bytes sha256 %s\n' "${f#"$PACK"/}" "$(stat -c %s "$f")" "$(sha256sum "$f" | cut -c1-16)"
    done
    for f in "$PACK"/debs/*/*.deb; do printf '%s\n' "${f#"$PACK"/}"; done
} >"$PACK/PACK_INFO"

say "packed: $PACK is $(mib "$(pack_bytes)"); with the working tree ($(mib "$TREE")) $(mib "$total") of 64 MiB"
du -sh "$PACK"/* | sed 's/^/[gpu-check-pack]   /'
cat <<EOF

On the device machine (one call; the datasets are made there, in data/):

  carry:     ["$PACK"]
  command:   $([[ $PACK != .gpu-check ]] && printf 'GPU_CHECK_PACK=%s ' "$PACK")GPU_CHECK_BUDGET_S=540 bash tools/scripts/gpu-check.sh
  timeout_s: 600

Its files come back from \$OUT: gpu-check.md, gpu-check.json, gpu-check.log, bind_cost.csv,
gpu-check-runs.tar.gz. Here, on lavapipe: GPU_CHECK_BUDGET_S=120 make gpu-check (writes out/gpu-check).
EOF
