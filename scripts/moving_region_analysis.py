#!/usr/bin/env python3
"""Where the moving pixels' error comes from, for one camera of a trained run.

Usage (numpy and ffmpeg; the renders from `acags render`, the ground truth from the dataset):

    acags dataset synth --preset fast --out fast-data
    acags render --run RUN --camera 1 --frames 0..40 --out RUN/render_cam01
    python3 scripts/moving_region_analysis.py fast-data RUN/render_cam01 1

Prints the moving / static PSNR (the evaluation's motion mask: the ground truth departs from
the camera's temporal median by more than 12/255 in some channel, dilated 2 px), the same split
into flat and textured pixels, and a *texture-matched* static PSNR: the static pixels' error per
decile of the moving pixels' image gradient, weighted as the moving pixels fall into those
deciles. Moving pixels are mostly object interiors and outlines while static pixels are mostly
flat wall and floor, so the plain gap mixes texture with motion; at matched texture what remains
is the moving objects' own deficit (docs/results.md, Follow-up 12). Comparing a training camera
with the test camera separates under-fitting (both low) from over-fitting (training high).

Then where the squared error lies, as shares of the whole clip's: on the *object* (pixels whose
ground truth departs from the median by more than 0.1), split into the part along the
background-to-object axis (the render a blend of object and background: the object faded or
partly missing) and the rest (wrong colour); and on *ghosts*: pixels whose ground truth is the
background (within 6/255 of the median) while the render departs from it by more than 0.1 —
on the object's path (pixels the object covers at some frame: remnants of it where it is not)
or off it, and the ghost rate of the path's background pixels by how many frames away the
object really covers them (a smear or lag shows near 0, remnants far away; the rate off the
path is the floor). Ghosts count as static pixels in the evaluation's split.
"""
import glob
import subprocess
import sys

import numpy as np

THRESHOLD = 12 / 255
DILATION = 2


def load(path):
    probe = subprocess.run(
        ["ffprobe", "-v", "quiet", "-select_streams", "v:0", "-show_entries",
         "stream=width,height", "-of", "csv=p=0", path],
        capture_output=True, text=True, check=True).stdout.strip()
    width, height = map(int, probe.split(","))
    raw = subprocess.run(
        ["ffmpeg", "-v", "quiet", "-i", path, "-f", "rawvideo", "-pix_fmt", "rgb24", "-"],
        capture_output=True, check=True).stdout
    if len(raw) != width * height * 3:
        sys.exit(f"{path}: could not decode a {width}x{height} RGB image")
    return np.frombuffer(raw, np.uint8).reshape(height, width, 3).astype(np.float32) / 255


def dilate(mask, r):
    padded = np.pad(mask, ((0, 0), (r, r), (r, r)))
    out = np.zeros_like(mask)
    for dy in range(2 * r + 1):
        for dx in range(2 * r + 1):
            out |= padded[:, dy:dy + mask.shape[1], dx:dx + mask.shape[2]]
    return out


def psnr(mse):
    return -10 * np.log10(max(mse, 1e-12))


def main():
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    data, renders, camera = sys.argv[1], sys.argv[2], int(sys.argv[3])
    frames = sorted(glob.glob(f"{renders}/[0-9][0-9][0-9][0-9][0-9].png"))
    if not frames:
        sys.exit(f"{renders}: no rendered frames (00000.png, ...) found")
    truth = []
    for f in range(len(frames)):
        # N3DV layout: png/camNN/ numbered from 00001 for the GOP's first frame.
        truth.append(load(f"{data}/png/cam{camera:02d}/{f + 1:05d}.png"))
    gt = np.stack(truth)
    rendered = np.stack([load(p) for p in frames])
    if rendered.shape != gt.shape:
        sys.exit(f"renders {rendered.shape} and ground truth {gt.shape} differ in size")
    median = np.median(gt, axis=0)
    moving = dilate(np.abs(gt - median).max(-1) > THRESHOLD, DILATION)
    error = ((gt - rendered) ** 2).mean(-1)
    gradient = np.zeros(gt.shape[:3], np.float32)
    gradient[:, :, 1:] += np.abs(gt[:, :, 1:] - gt[:, :, :-1]).sum(-1)
    gradient[:, 1:, :] += np.abs(gt[:, 1:, :] - gt[:, :-1, :]).sum(-1)
    textured = gradient >= np.median(gradient[moving])
    print(f"camera {camera}, {len(frames)} frames, {moving.mean() * 100:.1f} % moving")
    print(f"moving {psnr(error[moving].mean()):.2f} dB, static {psnr(error[~moving].mean()):.2f} dB")
    print(f"  flat: moving {psnr(error[moving & ~textured].mean()):.2f}, "
          f"static {psnr(error[~moving & ~textured].mean()):.2f}")
    print(f"  textured (gradient at or above the moving pixels' median): "
          f"moving {psnr(error[moving & textured].mean()):.2f}, "
          f"static {psnr(error[~moving & textured].mean()):.2f}")
    edges = np.quantile(gradient[moving], np.linspace(0, 1, 11))
    edges[0], edges[-1] = -np.inf, np.inf
    weights, static_mse = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        band = (gradient > lo) & (gradient <= hi)
        if (band & moving).sum() == 0 or (band & ~moving).sum() == 0:
            continue
        weights.append((band & moving).sum())
        static_mse.append(error[band & ~moving].mean())
    weights = np.array(weights, np.float64) / sum(weights)
    print(f"texture-matched static {psnr(float((weights * np.array(static_mse)).sum())):.2f} dB")
    ghosts_and_object(gt, rendered, median)


def ghosts_and_object(gt, rendered, median):
    departure, shown = gt - median, rendered - median
    squared = ((rendered - gt) ** 2).sum(-1)
    total = squared.sum()
    on_object = np.abs(departure).max(-1) > 0.1
    # The render projected on the median-to-truth axis: 1 = the object, 0 = the background.
    along = (shown * departure).sum(-1) / np.maximum((departure ** 2).sum(-1), 1e-9)
    fade = ((along - 1)[..., None] * departure) ** 2
    print(f"object pixels ({on_object.mean() * 100:.1f} %): {squared[on_object].sum() / total:.2f} "
          f"of the squared error, {fade.sum(-1)[on_object].sum() / total:.2f} along the "
          f"background-object axis; median blend {np.median(along[on_object]):.2f}, "
          f"share below 0.8: {np.mean(along[on_object] < 0.8):.2f}")
    path = on_object.any(0)
    background = np.abs(departure).max(-1) < 6 / 255
    ghost = background & (np.abs(shown).max(-1) > 0.1)
    on_path = ghost & path[None]
    print(f"ghosts ({ghost.mean() * 100:.1f} % of pixels): on the object's path "
          f"{squared[on_path].sum() / total:.2f} of the squared error, off it "
          f"{squared[ghost & ~path[None]].sum() / total:.2f}")
    # Ghost rate of the background pixels by how many frames away the object really covers
    # them: a smear or lag shows near 0, remnants far from it; the rate off the path (other
    # texture) is the floor.
    frames = np.arange(len(gt))
    bands = [(0, 1), (2, 4), (5, 16), (17, len(gt))]
    counts = np.zeros((len(bands), 2))
    for f in range(len(gt)):
        ys, xs = np.nonzero(background[f] & path)
        apart = np.where(on_object[:, ys, xs], np.abs(frames[:, None] - f), len(gt)).min(0)
        for b, (lo, hi) in enumerate(bands):
            inside = (apart >= lo) & (apart <= hi)
            counts[b] += [ghost[f, ys, xs][inside].sum(), inside.sum()]
    rates = ", ".join(f"{lo}-{hi} frames {n / max(m, 1):.3f}" for (lo, hi), (n, m) in zip(bands, counts))
    off = (background & ~path[None]).sum()
    print(f"  ghost rate on the path by frames to the object: {rates}; off the path "
          f"{(ghost & ~path[None]).sum() / max(off, 1):.3f}")


if __name__ == "__main__":
    main()
