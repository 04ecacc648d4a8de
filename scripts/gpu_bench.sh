#!/usr/bin/env bash
# Every GPU measurement issue 21 asks for, in one command on a GPU machine (NVIDIA, Vulkan):
#   - `bench raster` through wgpu (100k @ 512², 1M @ 1080p), the 1M forward against its
#     memory-bandwidth bound (docs/benchmarks.md derives the ~0.75 GB it must move at least);
#   - the same 1M case with ACAGS_KERNEL_TIMING=1 (each kernel stage waited for and timed);
#   - `bench train` through wgpu, with the share of the timed steps the GPU was busy
#     (nvidia-smi's utilization.gpu sampled every 100 ms: the share of each sample period in
#     which any kernel ran), and `bench train` on the machine's CPU (ndarray) for the ratio;
#   - the compositing backward with and without its subgroup sums (ACAGS_SUBGROUP_SUMS=0),
#     alternately, 1M @ 1080p;
#   - `bench lpips` through wgpu (AlexNet; VGG too where its weights are in ~/.cache/acags/lpips)
#     and on the CPU, at N3DV's evaluation size;
#   - optionally first the kernels' test binaries (wgpu_rasterizer, and the fused ops' columns,
#     counter_noise, fused_adam, gaussian_bits, cube_kernels) with ACAGS_REQUIRE_WGPU=1 and
#     ACAGS_REQUIRE_SUBGROUPS=1, so every CubeCL kernel and the GPU-only code paths are tested on
#     the GPU.
#
# Usage, in the repository root of the GPU machine (no Rust toolchain needed there):
#   scripts/gpu_bench.sh BIN OUTDIR [TEST_BIN [FIXTURES]]
# BIN is an acags binary built elsewhere (`strip`ped, optionally `.xz`); Debian's Vulkan loader
# and the glvnd/X11 client libraries, downloaded beside the checkout as `.gl/*.deb`, are
# unpacked into / first (docs/benchmarks.md, "GPU checks"). TEST_BIN likewise (built with
# `cargo test --release --workspace --test NAME --no-run`), or a `.tar.xz` of several such
# binaries, or a folder of them (each is run; stripped binaries share most of their code, so
# `tar cf - BINS | xz --lzma2=preset=6,dict=1GiB` packs six in ~33 MB); FIXTURES is the gsplat
# fixture folder they read (default ../shared/fixtures/gsplat). Results: OUTDIR/*.json, logs,
# the raw utilisation samples and summary.txt (the lent device machine returns only a few files
# from $OUT: write OUTDIR elsewhere, e.g. /tmp/gpu, then `tar czf $OUT/gpu.tgz -C /tmp gpu`).
# Budget: about 5 minutes on an H100, plus ~1 minute per test binary.
set -uo pipefail
bin=${1:?usage: scripts/gpu_bench.sh BIN OUTDIR [TEST_BIN [FIXTURES]]}
out=${2:?usage: scripts/gpu_bench.sh BIN OUTDIR [TEST_BIN [FIXTURES]]}
test_bin=${3:-}
fixtures=${4:-../shared/fixtures/gsplat}
mkdir -p "$out"
log() { echo "[gpu_bench $(date +%T)] $*"; }
# BIN, or BIN.xz decompressed, as an executable path.
unpacked() {
    if [[ $1 == *.xz ]]; then
        local to=/tmp/$(basename "$1" .xz)
        xz -dc "$1" >"$to" && chmod +x "$to" && echo "$to"
    else
        echo "$1"
    fi
}

if compgen -G ".gl/*.deb" >/dev/null; then
    for f in .gl/*.deb; do dpkg -x "$f" /; done
    ldconfig
fi
bin=$(unpacked "$bin") || exit 1
nvidia_icd=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
if ! ls /usr/share/vulkan/icd.d/*nvidia* /etc/vulkan/icd.d/*nvidia* >/dev/null 2>&1 &&
    [[ -f $nvidia_icd ]]; then
    export VK_DRIVER_FILES=$nvidia_icd
    export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
fi
nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm,clocks.max.memory \
    --format=csv | tee "$out/gpu.csv"
nproc | sed 's/^/host threads: /'

# Runs "$@" with GPU utilisation sampled to $out/util_$name.raw (nvidia-smi's timestamp, percent);
# records the command's end time in $out/end_$name.
sampled() {
    local name=$1 limit=$2
    shift 2
    nvidia-smi --query-gpu=timestamp,utilization.gpu --format=csv,noheader,nounits -lms 100 \
        >"$out/util_$name.raw" 2>/dev/null &
    local sampler=$!
    timeout "$limit" "$@" 2>&1 | tee "$out/log_$name.txt"
    local rc=${PIPESTATUS[0]}
    date +%s.%N >"$out/end_$name"
    kill $sampler 2>/dev/null
    wait $sampler 2>/dev/null
    log "$name: exit $rc"
}

run_test() {
    local name=$(basename "$1")
    log "test $name, fixtures $fixtures"
    ACAGS_REQUIRE_WGPU=1 ACAGS_REQUIRE_SUBGROUPS=1 ACAGS_FIXTURES=$(realpath "$fixtures") \
        timeout 240 "$1" --test-threads 1 2>&1 | tee "$out/log_test_$name.txt" |
        grep -E "^test |test result|panicked"
    log "test $name: exit ${PIPESTATUS[0]}"
}
if [[ -d $test_bin ]]; then
    for t in "$test_bin"/*; do run_test "$t"; done
elif [[ $test_bin == *.tar.xz ]]; then
    mkdir -p /tmp/gpu_tests
    xz -dc "$test_bin" | tar x -C /tmp/gpu_tests || exit 1
    for t in /tmp/gpu_tests/*; do run_test "$t"; done
elif [[ -n $test_bin ]]; then
    test_bin=$(unpacked "$test_bin") || exit 1
    run_test "$test_bin"
fi
log "raster, wgpu"
sampled raster 120 "$bin" bench raster --backend wgpu --json "$out/raster_wgpu.json"
log "raster 1M, wgpu, ACAGS_KERNEL_TIMING=1"
ACAGS_KERNEL_TIMING=1 sampled raster_stages 60 \
    "$bin" bench raster --backend wgpu --case 1M --json "$out/raster_wgpu_stages.json"
for round in 1 2; do
    for sums in 0 1; do
        log "raster 1M, subgroup sums $sums, round $round"
        ACAGS_SUBGROUP_SUMS=$sums timeout 60 "$bin" bench raster --backend wgpu --case 1M \
            --json "$out/raster_sums${sums}_round$round.json" >/dev/null 2>&1
    done
done
for net in alex vgg; do
    if [[ $net == vgg && ! -f ~/.cache/acags/lpips/vgg16.safetensors ]]; then continue; fi
    for backend in wgpu ndarray; do
        log "lpips $net, $backend"
        timeout 120 "$bin" bench lpips --backend $backend --net $net \
            --json "$out/lpips_${net}_$backend.json" 2>&1 | tail -3
    done
done
log "train, wgpu"
sampled train 200 "$bin" bench train --backend wgpu --steps 30 --json "$out/train_wgpu.json"
log "train, ndarray on $(nproc) threads"
sampled train_cpu 90 "$bin" bench train --backend ndarray --steps 30 \
    --json "$out/train_ndarray.json"

python3 - "$out" <<'EOF' | tee "$out/summary.txt"
import json, sys, os, datetime
out = sys.argv[1]
def load(name):
    path = os.path.join(out, name)
    return json.load(open(path)) if os.path.exists(path) else None
def util(name):
    rows = []
    for line in open(os.path.join(out, f"util_{name}.raw")):
        parts = [p.strip() for p in line.split(",")]
        try:
            t = datetime.datetime.strptime(parts[0], "%Y/%m/%d %H:%M:%S.%f").timestamp()
            rows.append((t, float(parts[1])))
        except (ValueError, IndexError):
            pass
    return rows
gpu = open(os.path.join(out, "gpu.csv")).read().splitlines()[-1]
print("GPU:", gpu)
# Peak DRAM bandwidth by board (nvidia-smi gives no bus width); override with ACAGS_GPU_BANDWIDTH.
bandwidth = float(os.environ.get("ACAGS_GPU_BANDWIDTH", 0)) or next(
    (bw for key, bw in [("H200", 4.8e12), ("H100 80GB HBM3", 3.35e12), ("H100 PCIe", 2.0e12),
                        ("H100 NVL", 3.9e12), ("A100-SXM4-80GB", 2.04e12)] if key in gpu), None)
raster = load("raster_wgpu.json")
if raster:
    for case in raster["cases"]:
        print(f"raster {case['name']}: forward {case['forward_ms']:.2f} ms, forward+backward "
              f"{case['forward_backward_ms']:.2f} ms, {case['intersections']} intersections, "
              f"fwd pairs/s {case['forward_pairs_per_second']:.3g}")
        if case["gaussians"] == 1_000_000 and bandwidth:
            bound_ms = 0.75e9 / bandwidth * 1e3
            print(f"  1M forward / bandwidth bound ({bound_ms:.3f} ms for 0.75 GB at "
                  f"{bandwidth/1e12:.2f} TB/s): {case['forward_ms'] / bound_ms:.1f}x")
for sums in (0, 1):
    runs = [load(f"raster_sums{sums}_round{r}.json") for r in (1, 2)]
    runs = [r["cases"][0] for r in runs if r]
    if runs:
        print(f"raster 1M, subgroup sums {'on' if sums else 'off'}: forward+backward "
              f"{[round(c['forward_backward_ms'], 2) for c in runs]} ms, forward "
              f"{[round(c['forward_ms'], 2) for c in runs]} ms")
for name, label in [("train_wgpu.json", "wgpu"), ("train_ndarray.json", "ndarray")]:
    report = load(name)
    if not report:
        print(f"train {label}: no result (see log)")
        continue
    print(f"train {label}: median {report['median_seconds_per_step']*1e3:.1f} ms/step, mean "
          f"{report['mean_seconds_per_step']*1e3:.1f}, {report['anchors']} anchors, "
          f"{report['gaussians']:.0f} Gaussians, threads {report['threads']}, cores busy "
          f"{report['average_cores_busy']}")
    print("  stages (median s):", {k: round(v, 4) for k, v in report["median_stage_seconds"].items()})
    print("  transfers per step:", report["transfers_per_step"])
    if label == "wgpu":
        end = float(open(os.path.join(out, "end_train")).read())
        timed = report["mean_seconds_per_step"] * report["timed_steps"]
        # The timed steps are the last `timed` seconds before the process ended (the JSON write
        # after them takes milliseconds).
        samples = [u for t, u in util("train") if end - timed <= t <= end]
        if samples:
            print(f"  GPU busy over the timed steps: {sum(samples)/len(samples):.1f} % "
                  f"({len(samples)} samples of nvidia-smi utilization.gpu)")
for net in ("alex", "vgg"):
    for backend in ("wgpu", "ndarray"):
        report = load(f"lpips_{net}_{backend}.json")
        if report:
            print(f"lpips {net} {backend} {report['width']}x{report['height']}: first "
                  f"{report['first_seconds']:.3f} s, median {report['median_seconds']*1e3:.1f} ms "
                  f"({report['repeats']} timed), load {report['load_seconds']:.2f} s")
wgpu, cpu = load("train_wgpu.json"), load("train_ndarray.json")
if wgpu and cpu:
    print(f"train step, ndarray/wgpu median: "
          f"{cpu['median_seconds_per_step'] / wgpu['median_seconds_per_step']:.2f}x")
EOF
