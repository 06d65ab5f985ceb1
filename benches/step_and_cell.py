#!/usr/bin/env python3
"""How a synthetic scene's re-simulation depends on the MPM step and cell (README *Physics
from video*, BENCHMARKS §8 diagnostics).

Simulates the scene's true frame-0 particles (`gt/particles/0.ply`) with `pipe simulate` at
the true material and initial velocity of `gt/params.json`, at several substep counts per
frame and grid cells, and prints, at the last frame, the mean distance of the material points
from the ground truth (numbered alike in every frame) and the centroid's height; then the
same at the maker's step and cell with Young's modulus scaled, to compare what E does with
what the discretisation does.

    python3 benches/step_and_cell.py SCENE [CELL ...]

SCENE: a folder of ../shared/datasets (e.g. ../shared/datasets/blob-plasticine); CELL: extra
grid cells (m) to try besides the maker's (default 0.0134, the `standard` preset's cell on
the blob). Needs numpy; `pipe` on PATH or in $PIPE. About a minute on 2 cores.
"""
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

FAMILY = {"elasticity": "elastic", "von_mises": "plasticine", "viscous_fluid": "newtonian"}


def read_ply(path):
    data = open(path, "rb").read()
    start = data.index(b"end_header\n") + len(b"end_header\n")
    return np.frombuffer(data[start:], dtype="<f4").reshape(-1, 3).astype(np.float64)


def sim_yaml(gt, dx, steps, e_scale=1.0, prefer=False):
    fam = FAMILY[gt["material"]]
    m = [f"  family: {fam}", f"  density: {gt['rho']}"]
    if fam == "newtonian":
        m += [f"  viscosity: {gt['mu']}", f"  bulk_modulus: {gt['kappa']}"]
    else:
        m += [f"  youngs_modulus: {gt['E'] * e_scale}", f"  poisson_ratio: {gt['nu']}"]
    if fam == "plasticine":
        m += [f"  yield_stress: {gt['yield_stress']}", f"  viscosity: {gt['plastic_viscosity_eta']}"]
    text = "material:\n" + "\n".join(m) + "\n"
    text += f"initial_velocity: {gt['v0']}\ngravity: {gt['gravity']}\n"
    text += f"frame_dt: {gt['frame_dt']}\ngrid_dx: {dx}\n"
    text += "boundaries:\n  - {kind: ground, y: 0, condition: sticky}\n"
    if steps is not None and prefer:
        text += f"prefer_substeps: {steps}\n"
    elif steps is not None:
        text += f"substeps: {steps}\nallow_unstable: true\n"
    return text


def main():
    if len(sys.argv) < 2:
        sys.exit(__doc__)
    scene = sys.argv[1]
    cells = [float(c) for c in sys.argv[2:]] or [0.0134]
    pipe = os.environ.get("PIPE", "pipe")
    gt = json.load(open(os.path.join(scene, "gt", "params.json")))
    parts = os.path.join(scene, "gt", "particles")
    last = gt["n_frames"] - 1
    truth = read_ply(os.path.join(parts, f"{last}.ply"))
    maker_dx, maker_steps = gt["dx"], gt["substeps"]
    cases = [(f"dx {maker_dx} m, automatic substeps", maker_dx, None, 1.0, False)]
    cases += [(f"dx {maker_dx} m, {n} substeps", maker_dx, n, 1.0, False)
              for n in (maker_steps // 2, maker_steps, 2 * maker_steps, 4 * maker_steps)]
    cases += [(f"dx {c} m, {maker_steps} substeps", c, maker_steps, 1.0, False) for c in cells]
    if gt.get("E"):
        # A stiffer trial may need more substeps than the maker's: `prefer_substeps`, as the
        # physics stages take them.
        cases += [(f"dx {maker_dx} m, prefer {maker_steps}, E x {s}", maker_dx, maker_steps, s,
                   True) for s in (3.0, 10.0, 50.0)]
    print(f"truth at frame {last}: centroid height {truth[:, 1].mean() * 1e3:.1f} mm "
          f"(made at dx {maker_dx} m, {maker_steps} substeps a frame)")
    with tempfile.TemporaryDirectory() as tmp:
        for k, (name, dx, steps, e_scale, prefer) in enumerate(cases):
            sim = os.path.join(tmp, f"{k}.yaml")
            open(sim, "w").write(sim_yaml(gt, dx, steps, e_scale, prefer))
            out = os.path.join(tmp, f"out{k}")
            subprocess.run([pipe, "simulate", os.path.join(parts, "0.ply"), "--material", sim,
                            "--frames", str(last + 1), "--out", out, "--quiet"],
                           check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            x = read_ply(os.path.join(out, f"frame_{last:04d}.ply"))
            off = np.linalg.norm(x - truth, axis=1).mean()
            print(f"{name:45s} material points {off * 1e3:5.2f} mm off, "
                  f"centroid height {x[:, 1].mean() * 1e3:5.1f} mm")


if __name__ == "__main__":
    main()
