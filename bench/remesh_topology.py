"""One SDF-remesh of an unchanged surface, per mesh and marching-cubes method: the total VNC-AUC ``S`` change and the
Euler characteristics on the way (issue 21, deliverable 1; boot.obj lost 4 handles and 5.3 % of ``S`` on CUDA only).

For each mesh (its face count, capped as VNC-Flow's bench caps it): the first remesh of the input (what VNC-Flow's
stage 0 is), then one more remesh of that result at its own positions (what every stage boundary does), and ``S``
(Eq. 4 summed over vertices, the flow's 16 scales of stage 0) before and after that second remesh. Printed per row:
the input's Euler characteristic, the Euler characteristics of the first grid's level set (marching cubes of the
signed distance, and of its negation: the two ways of resolving ambiguous cube faces), the result's, the second
remesh's path and why, and the ``S`` change. Writes ``OUT/remesh_topology.json``.

With ``--force-level-set`` the second remesh takes the marching-cubes path whatever the surface's level set says
(what a stage boundary with a contact join or a self-intersection does to the rest of the surface), and each row
also gives the edge-length spread (std / mean) before and after: ``S`` grows with it (Eq. (3) is a length-weighted
mean of dihedral angles), so a change of ``S`` that follows it is the tessellation's, not lost detail.

    python -m bench.remesh_topology --names boot.obj sword.obj --device cuda --out /tmp/rt
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings

import numpy as np

_HERE = os.path.dirname(os.path.abspath(__file__))


def level_set_eulers(remesher, mesh) -> tuple[int, int]:
    """Euler characteristics of the first grid's level set of ``mesh`` at the remesher's spacing: marching cubes of
    the signed distance and of its negation."""
    import warp as wp

    from vnc_warp import remesh as R

    dev = remesher.device
    x = wp.array(mesh.local_vertices, dtype=wp.vec3, device=dev)
    tri = wp.array(mesh.faces.reshape(-1).astype(np.int32), dtype=wp.int32, device=dev)
    wm = wp.Mesh(points=x, indices=tri, support_winding_number=True)
    lo, hi = R._device_bounds(x)
    area = float(R._area_and_centroid(mesh.local_vertices.astype(np.float64), mesh.faces)[0])
    clock = R._Clock(dev, {})
    ls = R._level_set(wm, lo, hi, remesher.spacing, R._GRIDS[0][0], area, remesher.use_winding, remesher.method,
                      clock)
    return ls.euler, (ls.joined().euler if hasattr(ls, "joined") else None)


def edge_spread(mesh) -> float:
    """Standard deviation over mean of the edge lengths of ``mesh``."""
    e = mesh.topology.edges
    length = np.linalg.norm(mesh.vertices[e[:, 0]] - mesh.vertices[e[:, 1]], axis=1)
    return float(length.std() / length.mean())


def one(path: str, faces: int | None, device: str, method: str, *, force_level_set: bool = False) -> dict:
    import warp as wp

    from vnc_warp.flow import _as_saved, total_complexity
    from vnc_warp.mesh import load_mesh
    from vnc_warp.remesh import _Remesher
    from vnc_warp.scale import default_scales

    name = os.path.basename(path)
    row = {"mesh": name, "method": method, "device": device}
    try:
        src = load_mesh(path)
        row["euler_input"] = int(src.num_vertices - src.topology.edges.shape[0] + src.num_faces)
        remesher = _Remesher(faces=faces, device=device, marching_cubes=method, warn=False)
        t0 = time.perf_counter()
        m0, rep0 = remesher(path)
        row.update(first_seconds=time.perf_counter() - t0, spacing=rep0.spacing, faces=rep0.faces,
                   first_method=rep0.method, first_why=rep0.why_level_set, euler_first=rep0.euler,
                   topology_passes=rep0.topology_passes)
        m0 = _as_saved(m0)
        taus = default_scales(m0, 16)
        S0 = total_complexity(m0, taus, device=device)
        e_sep, e_join = level_set_eulers(remesher, m0)
        row.update(euler_grid_separated=e_sep, euler_grid_joined=e_join)
        if force_level_set:
            disagreement, calls = remesher._disagreement, []

            def forced(*a, **kw):  # the first check of this call only; the topology passes after it as usual
                calls.append(1)
                return "forced (--force-level-set)" if len(calls) == 1 else disagreement(*a, **kw)

            remesher._disagreement = forced
        t0 = time.perf_counter()
        m1, rep1 = remesher(positions=wp.array(m0.local_vertices, dtype=wp.vec3, device=device))
        row.update(edge_spread0=edge_spread(m0), edge_spread1=edge_spread(_as_saved(m1)))
        row.update(again_seconds=time.perf_counter() - t0, again_method=rep1.method, again_why=rep1.why_level_set,
                   euler_again=rep1.euler)
        S1 = total_complexity(m1, taus, device=device)
        row.update(S0=S0, S1=S1, dS=S1 / S0 - 1.0)
    except Exception as exc:  # a failing mesh is a row of the table, not the end of the run
        row["error"] = f"{type(exc).__name__}: {exc}"
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--meshes", default=os.path.join(_HERE, "..", "..", "shared", "data", "meshes"),
                    help="folder of the real meshes")
    ap.add_argument("--names", nargs="*", default=["boot.obj", "sword.obj"])
    ap.add_argument("--methods", nargs="*", default=["auto"], help="marching cubes: auto, warp, skimage")
    ap.add_argument("--max-faces", type=int, default=50000, help="cap on each input's face count (0: none)")
    ap.add_argument("--force-level-set", action="store_true",
                    help="the second remesh takes the marching-cubes path (see above)")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    import warp as wp

    from vnc_warp.mesh import load_mesh

    device = args.device or str(wp.get_preferred_device())
    os.makedirs(args.out, exist_ok=True)
    rows = []
    header = (f"{'mesh':<14} {'mc':<8} {'faces':>6} {'h':>9} {'euler in':>8} {'grid sep/join':>13} {'first':>5} "
              f"{'again':>5} {'paths':<17} {'dS one remesh':>13} {'s':>6} {'edge spread':<11}  why")
    print(header)
    for name in args.names:
        path = os.path.join(args.meshes, name)
        faces = None
        if args.max_faces:
            n = load_mesh(path).num_faces
            faces = n if n <= args.max_faces else args.max_faces
        for method in args.methods:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                row = one(path, faces, device, method, force_level_set=args.force_level_set)
            rows.append(row)
            if "error" in row and "dS" not in row:
                print(f"{name:<14} {method:<8} error: {row['error']}")
                continue
            print(f"{name:<14} {method:<8} {row['faces']:>6} {row['spacing']:>9.3g} {row['euler_input']:>8} "
                  f"{row['euler_grid_separated']:>6}/{str(row['euler_grid_joined']):<6} {row['euler_first']:>5} "
                  f"{row['euler_again']:>5} {row['first_method'] + '/' + row['again_method']:<17} {100 * row['dS']:>+12.2f}% "
                  f"{row['first_seconds'] + row['again_seconds']:>6.1f} {row['edge_spread0']:>5.3f}>{row['edge_spread1']:<5.3f}"
                  f"  {row['again_why'] or ''}")
    out = os.path.join(args.out, "remesh_topology.json")
    with open(out, "w") as fh:
        json.dump({"device": device, "rows": rows}, fh, indent=1)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
