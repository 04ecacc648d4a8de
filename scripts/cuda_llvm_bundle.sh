#!/usr/bin/env bash
# The `cuda` feature offline: cubecl-cuda compiles through cubecl-llvm, whose build dependency
# tracel-llvm-bundler downloads a prebuilt LLVM the first time it builds (README, "Backends").
# Its build script also accepts the bundle already in its cache directory, so a machine without
# network (the lent GPU machines, an air-gapped cluster) can build `--features cuda` with two
# files carried over:
#
#   on a machine with network, in the checkout:   scripts/cuda_llvm_bundle.sh fetch DIR
#   carry DIR over; on the offline machine:       scripts/cuda_llvm_bundle.sh install DIR
#   then build there with the variable it prints: TRACEL_LLVM_BUNDLER_SKIP_CHECKSUM_DOWNLOAD=1 \
#                                                   cargo build --release --features cuda
#
# The version is the LLVM release the locked bundler crate downloads (its TRACEL_LLVM_VERSION and
# TRACEL_LLVM_RELEASE_NUMBER when its source is in cargo's registry, else its crate version,
# equal for 23.1.0-4), the platform from
# `uname` (linux-x64, linux-AArch64, macos-x64, macos-AArch64). `fetch` downloads
#   https://github.com/tracel-ai/tracel-llvm/releases/download/v<version>/<platform>.tar.xz
#   and <platform>.checksums.json (a JSON sidecar with archive_sha256 and content_sha256),
# and checks the archive against the sidecar. `install` checks it again and copies both into
# ~/.cache/tracel/ under the names the build script looks for:
#   tracel-llvm-<version>-<platform>.tar.xz and tracel-llvm-<version>-<platform>.checksums.json.
# With TRACEL_LLVM_BUNDLER_SKIP_CHECKSUM_DOWNLOAD set, the build script reads the sidecar from
# there instead of downloading it, finds the archive's checksum equal (a mismatch makes it try to
# download again, which fails offline), extracts it into the platform's data directory
# (Linux: ${XDG_DATA_HOME:-~/.local/share}/tracel/tracel-llvm-<version>/; macOS: ~/Library/
# Application Support/tracel/...), checks the extracted tree's
# content checksum and leaves a sentinel (.tracel-llvm-installed) there; later builds see the
# sentinel and skip all of it (so copying an already extracted folder with its sentinel works too).
# Checked offline (2026-11-29, tracel-llvm-bundler 23.1.0-4): a stand-in bundle with matching
# sidecar checksums, installed by this script into a fresh HOME, was extracted by the build
# script of `cargo check --features cuda` with its sentinel written, no network reached.
# Type-checking needs none of this: `DOCS_RS=1 cargo check --release --workspace --features cuda`.
set -euo pipefail

die() { echo "cuda_llvm_bundle.sh: $*" >&2; exit 1; }

root=$(cd "$(dirname "$0")/.." && pwd)
lock="$root/Cargo.lock"
[ -f "$lock" ] || die "no Cargo.lock at $lock"
version=$(awk '/^name = "tracel-llvm-bundler"$/ { getline; gsub(/version = |"/, ""); print; exit }' "$lock")
[ -n "$version" ] || die "$lock names no tracel-llvm-bundler (is the cuda feature's dependency tree locked?)"
# What the bundler's build script itself downloads, where its source is at hand.
for config in "${CARGO_HOME:-$HOME/.cargo}"/registry/src/*/"tracel-llvm-bundler-$version"/src/config.rs; do
    [ -f "$config" ] || continue
    llvm=$(sed -n 's/.*TRACEL_LLVM_VERSION: &str = "\(.*\)";/\1/p' "$config")
    release=$(sed -n 's/.*TRACEL_LLVM_RELEASE_NUMBER: &str = "\(.*\)";/\1/p' "$config")
    [ -n "$llvm" ] && [ -n "$release" ] || die "$config no longer names TRACEL_LLVM_VERSION / TRACEL_LLVM_RELEASE_NUMBER"
    version="$llvm-$release"
    break
done

case "$(uname -s)-$(uname -m)" in
    Linux-x86_64) platform=linux-x64 ;;
    Linux-aarch64 | Linux-arm64) platform=linux-AArch64 ;;
    Darwin-x86_64) platform=macos-x64 ;;
    Darwin-arm64) platform=macos-AArch64 ;;
    *) die "no tracel-llvm bundle for $(uname -s) $(uname -m)" ;;
esac
usage="usage: $0 fetch|install DIR [--platform NAME]"
command=${1:-}
dir=${2:-}
[ -n "$dir" ] || die "$usage"
# `--platform NAME` fetches another machine's bundle (e.g. linux-x64 from a Mac).
case "$#:${3:-}" in
    2:) ;;
    4:--platform)
        platform=$4
        case "$platform" in
            linux-x64 | linux-AArch64 | macos-x64 | macos-AArch64 | windows-x64 | windows-AArch64) ;;
            *) die "unknown platform '$platform' (linux-x64, linux-AArch64, macos-x64, macos-AArch64, windows-x64, windows-AArch64)" ;;
        esac
        ;;
    *) die "$usage" ;;
esac

archive="$platform.tar.xz"
sidecar="$platform.checksums.json"

sha256() { sha256sum "$1" 2>/dev/null | cut -d' ' -f1 || shasum -a 256 "$1" | cut -d' ' -f1; }

# The archive checksum the sidecar expects.
expected_sha() {
    local file=$1
    python3 - "$file" <<'EOF' 2>/dev/null || sed -n 's/.*"archive_sha256"[[:space:]]*:[[:space:]]*"\([0-9a-fA-F]*\)".*/\1/p' "$file"
import json, sys
print(json.load(open(sys.argv[1], encoding="utf-8-sig"))["archive_sha256"])
EOF
}

verify() {
    local dir=$1
    [ -f "$dir/$archive" ] || die "no $dir/$archive (run 'fetch' on a machine with network first)"
    [ -f "$dir/$sidecar" ] || die "no $dir/$sidecar (run 'fetch' on a machine with network first)"
    local want got
    want=$(expected_sha "$dir/$sidecar")
    [ -n "$want" ] || die "$dir/$sidecar has no archive_sha256 (not a tracel-llvm checksum sidecar?)"
    got=$(sha256 "$dir/$archive")
    [ "$want" = "$got" ] || die "$dir/$archive has sha256 $got, but $dir/$sidecar expects $want (a partial download or another release)"
}

case "$command" in
    fetch)
        mkdir -p "$dir"
        base="https://github.com/tracel-ai/tracel-llvm/releases/download/v$version"
        for file in "$sidecar" "$archive"; do
            echo "downloading $base/$file"
            curl -fL --retry 3 -o "$dir/$file.part" "$base/$file" || die "could not download $base/$file"
            mv "$dir/$file.part" "$dir/$file"
        done
        verify "$dir"
        echo "tracel-llvm $version ($platform) in $dir, checksum verified; carry the folder and run: $0 install DIR"
        ;;
    install)
        verify "$dir"
        cache="$HOME/.cache/tracel"
        mkdir -p "$cache"
        cp "$dir/$archive" "$cache/tracel-llvm-$version-$archive"
        cp "$dir/$sidecar" "$cache/tracel-llvm-$version-$sidecar"
        echo "installed into $cache; build with:"
        echo "  TRACEL_LLVM_BUNDLER_SKIP_CHECKSUM_DOWNLOAD=1 cargo build --release --features cuda"
        ;;
    *) die "$usage" ;;
esac
