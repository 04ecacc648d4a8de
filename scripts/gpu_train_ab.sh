#!/usr/bin/env bash
# `bench train` through wgpu for several acags binaries, alternately, on a GPU machine: the
# side-by-side measurement a change to the training step needs (docs/benchmarks.md). Prepared
# for the statistics-on-the-device change (host statistics / Burn's select_assign / the atomic
# scatter kernel), whose GPU effect is still unmeasured: no device could be started in that
# session.
#
# Usage, in the repository root of the GPU machine:
#   scripts/gpu_train_ab.sh PACK OUTDIR [ROUNDS]
# PACK is a `.tar.xz` of stripped binaries (`tar cf - acags-* test_* | xz --lzma2=preset=6,dict=1GiB`;
# three acags binaries and two test binaries pack into ~44 MB): each `acags-NAME` is timed, each
# `test_*` test binary is run first with ACAGS_REQUIRE_WGPU=1 ACAGS_REQUIRE_SUBGROUPS=1. Debian's
# Vulkan loader and the glvnd/X11 libraries in `.gl/*.deb` are unpacked into / first (the
# *GPU checks* recipe). Per round and binary: the default config with the densification window
# open over the timed steps, and the plain step; then ACA-GS with its windows open, one round.
# Copy OUTDIR into $OUT as one archive (the device returns only a few files).
set -uo pipefail
pack=${1:?usage: scripts/gpu_train_ab.sh PACK OUTDIR [ROUNDS]}
out=${2:?usage: scripts/gpu_train_ab.sh PACK OUTDIR [ROUNDS]}
rounds=${3:-2}
mkdir -p "$out" /tmp/ab_bins
if compgen -G ".gl/*.deb" >/dev/null; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
if ! ls /usr/share/vulkan/icd.d/*nvidia* /etc/vulkan/icd.d/*nvidia* >/dev/null 2>&1; then
    export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
xz -dc "$pack" | tar x -C /tmp/ab_bins || exit 1
nvidia-smi --query-gpu=name,driver_version --format=csv | tee "$out/gpu.csv"
log() { echo "[gpu_train_ab $(date +%T)] $*"; }
for t in /tmp/ab_bins/test_*; do
    [[ -e $t ]] || continue
    log "test $(basename "$t")"
    ACAGS_REQUIRE_WGPU=1 ACAGS_REQUIRE_SUBGROUPS=1 timeout 150 "$t" --test-threads 1 2>&1 |
        tee "$out/log_$(basename "$t").txt" | grep -E "^test |test result|panicked"
done
window=(--set densify.start=40 --set densify.every=1000)
aca=(--config configs/aca-gs.toml --set aac.start=1000 --set aac.every=1000 --set aac.stop=1100)
bench() { # NAME BINARY ARGS...
    local name=$1 bin=$2
    shift 2
    log "$name"
    # The 1,600-step schedule (the default until 2026-12-05), so steps 52-71 are dynamic-phase
    # steps for binaries from before and after the default doubled.
    timeout 120 "$bin" bench train --backend wgpu --warmup 51 --steps 20 --set train.max_steps=1600 "$@" \
        --json "$out/$name.json" >"$out/log_$name.txt" 2>&1
    log "$name: exit $?"
}
bins=(/tmp/ab_bins/acags-*)
for round in $(seq 1 "$rounds"); do
    for b in "${bins[@]}"; do bench "window_$(basename "$b")_r$round" "$b" "${window[@]}"; done
    for b in "${bins[@]}"; do bench "plain_$(basename "$b")_r$round" "$b"; done
done
for b in "${bins[@]}"; do bench "aca_window_$(basename "$b")" "$b" "${window[@]}" "${aca[@]}"; done
python3 - "$out" <<'PY' | tee "$out/summary.txt"
import glob, json, os, sys
for path in sorted(glob.glob(os.path.join(sys.argv[1], "*.json"))):
    r = json.load(open(path))
    stages = {k: round(v * 1e3, 1) for k, v in r["median_stage_seconds"].items()}
    print(f"{os.path.basename(path)[:-5]}: median {r['median_seconds_per_step'] * 1e3:.1f} ms, mean "
          f"{r['mean_seconds_per_step'] * 1e3:.1f} ms, {r['anchors']} anchors, transfers "
          f"{r['transfers_per_step']}, stages (ms) {stages}")
PY
