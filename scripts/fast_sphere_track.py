#!/usr/bin/env python3
"""Per frame: where the exported Gaussians near the fast sphere sit against its true centre.
Usage: fast_sphere_track.py EXPORT_DIR, the directory `acags export --run RUN` writes for a run
of synthetic:fast (the sphere's path below is `fast_sphere_center` of src/data/synthetic.rs for
that preset: travel 4, bounce 0.8, 40 frames). Columns: the opacity-weighted centroid of the
Gaussians within 0.6 of the true centre (floor excluded) minus the true centre (y points down),
their mean distance from the centre minus the radius, and its RMS."""
import sys, os, math, numpy as np
R, FLOOR, TRAVEL, BOUNCE, FRAMES = 0.35, 1.0, 4.0, 0.8, 40
def centre(t):
    b = BOUNCE * abs(math.sin(t * math.pi * 2))
    return np.array([-TRAVEL / 2 + TRAVEL * t, FLOOR - R - b, 3.2])
def read_ply(p):
    with open(p, 'rb') as f:
        props, n = [], 0
        while True:
            line = f.readline().decode().strip()
            if line.startswith('element vertex'): n = int(line.split()[-1])
            elif line.startswith('property'): props.append(line.split()[-1])
            elif line == 'end_header': break
        a = np.frombuffer(f.read(n * 4 * len(props)), dtype='<f4').reshape(n, len(props))
    return {k: a[:, i] for i, k in enumerate(props)}
d = sys.argv[1]
print("frame | true y | n | centroid-true dx dy dz | mean |d|-R (shell) | rms radial")
for f in range(FRAMES):
    g = read_ply(os.path.join(d, f"frame_{f:05d}.ply"))
    p = np.stack([g['x'], g['y'], g['z']], 1)
    op = 1 / (1 + np.exp(-g['opacity']))
    c = centre(f / (FRAMES - 1))
    r = np.linalg.norm(p - c, axis=1)
    sel = (r < 0.6) & (p[:, 1] < FLOOR - 0.03)
    w = op[sel]
    cen = (p[sel] * w[:, None]).sum(0) / w.sum()
    shell = ((r[sel] - R) * w).sum() / w.sum()
    rms = math.sqrt(((r[sel] - R) ** 2 * w).sum() / w.sum())
    dd = cen - c
    print(f"{f} | {c[1]:.3f} | {sel.sum()} | {dd[0]:+.3f} {dd[1]:+.3f} {dd[2]:+.3f} | {shell:+.3f} | {rms:.3f}")
