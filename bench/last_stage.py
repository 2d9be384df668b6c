"""How well can a trajectory's last stage be predicted from its first? Oracles for issue 24's t = 0 comparison.

    python -m bench.last_stage TRAJ_DIR [TRAJ_DIR ...] --out OUT

At t = 0 the latent-interpolation baseline decodes the VAE's code of the ground-truth last stage: it is given the
answer, and its CD is the VAE's reconstruction error of that stage. C-VAE-I must predict the same surface from
stage 0. This scores the last stage of each trajectory (package frame: stage 0's box at max extent 1.8; CD on
``--points`` area-weighted samples, as the experiment's evaluation) against surfaces built from what is known:

* ``floor``: the last stage resampled (the sampling floor);
* ``sphere, stage-0 area``: the sphere of stage 0's area at stage 0's centroid (a rule using the input only);
* ``sphere, own area and centroid``: the sphere of the last stage's own area at its own centroid (an oracle of
  its size and place: the best any prediction of "a sphere" can do);
* ``ellipsoid, own moments``: the ellipsoid of the last stage's own second moments, scaled to its area (an
  oracle of its size, place, axes and orientation).

Prints a table and writes ``OUT/last_stage.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import numpy as np
import trimesh

from vnc_warp.remesh import moment_ellipsoid
from vnc_warp.trajectory import read_trajectory
from vnc_warp.training.data import normalization
from vnc_warp.training.metrics import _sample, _scores, compare_meshes


def _sphere(radius: float, centre: np.ndarray) -> trimesh.Trimesh:
    s = trimesh.creation.icosphere(subdivisions=6, radius=radius)
    s.apply_translation(centre)
    return s


def _moment_ellipsoid(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    """The ellipsoid with the solid's centroid, principal axes and axis ratios (:func:`vnc_warp.remesh.moment_ellipsoid`),
    scaled to the mesh's area."""
    c, axes, radii, _ = moment_ellipsoid(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces))
    e = trimesh.creation.icosphere(subdivisions=6, radius=1.0)
    e.apply_transform(np.diag(np.r_[radii, 1.0]))
    e.apply_scale(np.sqrt(mesh.area / e.area))
    e.apply_transform(np.block([[axes, c[:, None]], [np.zeros((1, 3)), np.ones((1, 1))]]))
    return e


def score(traj_dir: str, *, points: int, seed: int = 0) -> dict:
    """CD x1e-4 (package frame) of the trajectory's last stage against each oracle of the module docstring."""
    traj = read_trajectory(traj_dir)
    first, last = traj.load_stage(0), traj.load_stage(len(traj.stages) - 1)
    norm = normalization(first)
    m0 = trimesh.Trimesh(first.vertices, first.faces, process=False)
    mf = trimesh.Trimesh(last.vertices, last.faces, process=False)
    out = {"trajectory": str(traj.root), "stages": len(traj.stages), "t_last": float(traj.t[-1]),
           "floor": _scores(_sample(mf, "last", points, seed + 1, norm), _sample(mf, "last", points, seed, norm),
                            1, True)["cd_x1e4"]}
    candidates = {"sphere, stage-0 area": _sphere(np.sqrt(m0.area / (4 * np.pi)), m0.center_mass),
                  "sphere, own area and centroid": _sphere(np.sqrt(mf.area / (4 * np.pi)), mf.center_mass),
                  "ellipsoid, own moments": _moment_ellipsoid(mf)}
    for name, cand in candidates.items():
        out[name] = compare_meshes(cand, mf, n_points=points, n_emd=1, seed=seed, normalization=norm)["cd_x1e4"]
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("trajectories", nargs="+", help="trajectory folders (manifest.json and stage files)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--points", type=int, default=100_000, help="samples per surface (CD)")
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    rows = [score(d, points=args.points) for d in args.trajectories]
    cols = ["floor", "sphere, stage-0 area", "sphere, own area and centroid", "ellipsoid, own moments"]
    print("| trajectory | stages | last t | " + " | ".join(cols) + " |")
    print("|---|---|---|" + "---|" * len(cols))
    for r in rows:
        print(f"| {os.path.basename(r['trajectory'].rstrip('/'))} | {r['stages'] - 1} | {r['t_last']:.3f} | "
              + " | ".join(f"{r[c]:.2f}" for c in cols) + " |")
    with open(os.path.join(args.out, "last_stage.json"), "w") as fh:
        json.dump({"command": " ".join(["python -m bench.last_stage"] + (argv or sys.argv[1:])),
                   "units": "CD x1e-4, package frame", "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
