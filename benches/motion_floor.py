#!/usr/bin/env python3
"""What the torus-elastic bounce alone costs in held-out PSNR (BENCHMARKS §8, issue 24's mark).

The scene's truth is one random sampling of a torus (`gt/particles/0.ply`: uniform random
points, nearest-neighbour distance 2-9 mm), simulated by PAC-NeRF's MPM; its bounce depends on
that sampling, which no image shows. This script renders one set of fitted Gaussians (a 3DGS
PLY, e.g. `pipe export pipelines/torus-elastic.yaml --stage warmup --format ply --out g.ply`)
carried by two motions, and scores one against the other from the held-out camera:

- the truth's motion: each Gaussian follows the affine fit of its 12 nearest true particles'
  displacement (`gt/particles/<f>.ply`, numbered alike in every frame);
- the motion of the *exact* torus (its radii from `gt/params.json`, its pose from the true
  particles) sampled afresh (`--sampler jittered`, the default: one random point in every voxel
  of edge dx/2, the maker's own sampling statistics; `uniform`: as many uniform random points;
  seeds `--seeds`), simulated by `pipe simulate` with the true material and velocity at the
  maker's cell and step.

Both renders have the same Gaussians and colours (SH degree 0: a turned body's view-dependent
colour is not what is measured), so their PSNR is what the motion alone costs: the best any
re-simulation of the scene could score, even with the exact shape, material and velocity and a
perfect appearance. With `--frame0-psnr P` (a run's held-out PSNR at frame 0, where the motion
is exact and only appearance differs) it also prints the per-frame total `-10 log10(10^(-m/10)
+ 10^(-P/10))` and its mean over the frames.

    python3 benches/motion_floor.py SCENE GAUSSIANS.ply [--view 10] [--frame0-psnr 35.06] [--seeds 1 2 ...]
        [--sampler jittered|uniform]

Needs numpy, scipy and pillow; `pipe` on PATH or in $PIPE. About 20 s a seed.
"""
import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np
from PIL import Image
from scipy.spatial import cKDTree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bounce_sensitivity import jittered_torus, read_ply, resampled_torus, write_ply  # noqa: E402

NEIGHBOURS = 12

SIM = """material: {{family: elastic, youngs_modulus: {E}, poisson_ratio: {nu}, density: {rho}}}
initial_velocity: [{v0[0]}, {v0[1]}, {v0[2]}]
gravity: [0, -9.8, 0]
frame_dt: {frame_dt}
grid_dx: {dx}
prefer_substeps: {substeps}
fill_interior: false
boundaries:
  - {{kind: ground, y: 0, condition: sticky}}
"""


def read_gaussians(path):
    raw = open(path, "rb").read()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    names = [l.split()[-1].decode() for l in raw[:end].split(b"\n") if l.startswith(b"property")]
    g = np.frombuffer(raw[end:], dtype="<f4").reshape(-1, len(names)).astype(np.float64)
    return raw[:end], names, g


def quat_to_matrix(q):
    w, x, y, z = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def matrix_to_quat(m):
    """Rotation matrices (proper; a reflection is flipped first) to quaternions (w, x, y, z)."""
    out = np.zeros((len(m), 4))
    for k, r in enumerate(m):
        if np.linalg.det(r) < 0:
            r = r.copy()
            r[:, 2] *= -1
        t = np.trace(r)
        if t > 0:
            s = 2 * np.sqrt(t + 1)
            out[k] = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
        elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
            s = 2 * np.sqrt(1 + r[0, 0] - r[1, 1] - r[2, 2])
            out[k] = [(r[2, 1] - r[1, 2]) / s, 0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s]
        elif r[1, 1] > r[2, 2]:
            s = 2 * np.sqrt(1 + r[1, 1] - r[0, 0] - r[2, 2])
            out[k] = [(r[0, 2] - r[2, 0]) / s, (r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s]
        else:
            s = 2 * np.sqrt(1 + r[2, 2] - r[0, 0] - r[1, 1])
            out[k] = [(r[1, 0] - r[0, 1]) / s, (r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s]
    return out


class Carrier:
    """Gaussians carried by a particle motion (the affine fit of their nearest particles')."""

    def __init__(self, names, g):
        self.names, self.g = names, g
        col = {n: i for i, n in enumerate(names)}
        self.xyz = g[:, [col["x"], col["y"], col["z"]]]
        self.scale_cols = [col[f"scale_{i}"] for i in range(3)]
        self.rot_cols = [col[f"rot_{i}"] for i in range(4)]
        self.rest_cols = [i for i, n in enumerate(names) if n.startswith("f_rest_")]
        s = np.exp(g[:, self.scale_cols])
        r = quat_to_matrix(g[:, self.rot_cols])
        self.cov = r @ (s[:, :, None] ** 2 * np.transpose(r, (0, 2, 1)))

    def at(self, rest, now):
        idx = cKDTree(rest).query(self.xyz, k=NEIGHBOURS)[1]
        a, b = rest[idx], now[idx]
        ca, cb = a.mean(1), b.mean(1)
        x, y = a - ca[:, None], b - cb[:, None]
        # Per Gaussian: A = argmin |x A^T - y|, by the normal equations.
        xtx = np.einsum("gki,gkj->gij", x, x)
        xty = np.einsum("gki,gkj->gij", x, y)
        affine = np.transpose(np.linalg.solve(xtx, xty), (0, 2, 1))
        out = self.g.copy()
        out[:, :3] = cb + np.einsum("gij,gj->gi", affine, self.xyz - ca)
        cov = affine @ self.cov @ np.transpose(affine, (0, 2, 1))
        w, v = np.linalg.eigh(cov)
        out[:, self.scale_cols] = 0.5 * np.log(np.maximum(w, 1e-14))
        out[:, self.rot_cols] = matrix_to_quat(v)
        out[:, self.rest_cols] = 0.0
        return out


def render(pipe, head, g, cameras, view, frame, path):
    ply = path + ".ply"
    open(ply, "wb").write(head + g.astype("<f4").tobytes())
    subprocess.run([pipe, "render", ply, "--cameras", cameras, "--view", str(view), "--frame",
                    str(frame), "--out", path + ".png", "--background", "0.5,0.5,0.5"],
                   check=True, stdout=subprocess.DEVNULL)
    return np.asarray(Image.open(path + ".png").convert("RGB")).astype(np.float64) / 255


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("scene")
    ap.add_argument("gaussians")
    ap.add_argument("--view", type=int, default=10)
    ap.add_argument("--frame0-psnr", type=float)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--sampler", choices=["jittered", "uniform"], default="jittered",
                    help="jittered: one random point per voxel of edge dx/2, the maker's sampling "
                    "statistics; uniform: uniform random points")
    a = ap.parse_args()
    pipe = os.environ.get("PIPE", "pipe")
    import json

    gt = json.load(open(os.path.join(a.scene, "gt", "params.json")))
    gt_dir = os.path.join(a.scene, "gt", "particles")
    frames = sorted(int(f[:-4]) for f in os.listdir(gt_dir) if f.endswith(".ply"))
    truth0 = read_ply(os.path.join(gt_dir, "0.ply"))
    head, names, g = read_gaussians(a.gaussians)
    carrier = Carrier(names, g)
    cameras = os.path.join(a.scene, "all_data.json")
    with tempfile.TemporaryDirectory() as tmp:
        sim = os.path.join(tmp, "true.sim.yaml")
        open(sim, "w").write(SIM.format(E=gt["E"], nu=gt["nu"], rho=gt["rho"], v0=gt["v0"],
                                        frame_dt=gt["frame_dt"], dx=gt["dx"],
                                        substeps=gt["substeps"]))
        samplings = {}
        radii = gt["shape"]["args"]["R"], gt["shape"]["args"]["r"]
        for seed in a.seeds:
            x = (jittered_torus(truth0, *radii, seed, h=gt["dx"] / 2) if a.sampler == "jittered"
                 else resampled_torus(truth0, *radii, seed))
            ply = os.path.join(tmp, f"resampled{seed}.ply")
            write_ply(ply, x)
            out = os.path.join(tmp, f"resampled{seed}")
            subprocess.run([pipe, "simulate", ply, "--material", sim, "--frames",
                            str(frames[-1] + 1), "--out", out, "--quiet"],
                           check=True, stdout=subprocess.DEVNULL)
            samplings[seed] = (x, out)
        rows = []
        for f in frames:
            ref = render(pipe, head, carrier.at(truth0, read_ply(os.path.join(gt_dir, f"{f}.ply"))),
                         cameras, a.view, f, os.path.join(tmp, f"truth_{f}"))
            row = []
            for seed, (x, out) in samplings.items():
                now = read_ply(os.path.join(out, f"frame_{f:04d}.ply"))
                img = render(pipe, head, carrier.at(x, now), cameras, a.view, f,
                             os.path.join(tmp, f"s{seed}_{f}"))
                mse = ((img - ref) ** 2).mean()
                row.append(10 * np.log10(1 / mse) if mse > 0 else float("inf"))
            rows.append(row)
    print(f"held-out view {a.view}: PSNR (dB) of the exact torus resampled (seeds {a.seeds}) "
          "against the true motion, same Gaussians")
    for f, row in zip(frames, rows):
        line = f"frame {f:2d}: " + "  ".join(f"{r:6.2f}" for r in row)
        if a.frame0_psnr is not None:
            tot = [-10 * np.log10(10 ** (-r / 10) + 10 ** (-a.frame0_psnr / 10)) for r in row]
            line += "   with frame 0's appearance: " + "  ".join(f"{t:6.2f}" for t in tot)
        print(line)
    if a.frame0_psnr is not None:
        for k, seed in enumerate(a.seeds):
            tot = [-10 * np.log10(10 ** (-row[k] / 10) + 10 ** (-a.frame0_psnr / 10)) for row in rows]
            print(f"seed {seed}: mean {np.mean(tot):.2f} dB, first {tot[0]:.2f}, last {tot[-1]:.2f}")
    last = sorted(rows[-1])
    print(f"motion alone at frame {frames[-1]}: median {np.median(last):.2f} dB, "
          f"best {last[-1]:.2f}, worst {last[0]:.2f} over {len(last)} samplings")


if __name__ == "__main__":
    main()
