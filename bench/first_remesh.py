"""The first SDF-remesh of real meshes at a face count (what VNC-Flow's stage 0 is), then one more remesh of that
result at its own positions (what every stage boundary does): grid spacing, path, what was dropped or lost, whether
and why the grid was refined for thin parts, the area change, the total VNC-AUC ``S`` (Eq. 4 summed over vertices, 16
scales of the input) of the input and of the result, the ``S`` change of the second remesh (16 scales of the result)
and seconds. A refused remesh is a row with its message. Writes ``OUT/first_remesh.json``.

The C-VAE experiment's ``gpu`` preset flows the real meshes at 6,000 faces on the automatic grid:

    python -m bench.first_remesh --names sword.obj bunny.obj human_man.obj --faces 6000 --device cpu --out /tmp/fr
"""

from __future__ import annotations

import argparse
import json
import os
import time

_HERE = os.path.dirname(os.path.abspath(__file__))


def first_remesh(path: str, faces: int | None, device, *, resolution: int | None = None,
                 allow_changes: bool = False) -> dict:
    import warp as wp

    from vnc_warp.flow import _as_saved, total_complexity
    from vnc_warp.mesh import MeshError, load_mesh
    from vnc_warp.remesh import _Remesher
    from vnc_warp.scale import default_scales

    src = load_mesh(path)
    row = {"mesh": os.path.basename(path), "faces_in": src.num_faces, "faces": faces, "allow_changes": allow_changes}
    remesher = _Remesher(faces=faces, resolution=resolution, device=device, allow_changes=allow_changes, warn=False)
    t0 = time.perf_counter()
    try:
        out, report = remesher(path)
    except MeshError as exc:
        return row | {"refused": str(exc), "seconds": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    d = report.to_dict()
    row |= {k: d[k] for k in ("method", "spacing", "faces", "vertices", "euler_in", "euler", "components_level_set",
                              "dropped_components", "dropped_area", "lost_area", "area_scale", "grid_refined",
                              "changes")}
    row["seconds"], row["seconds_parts"] = seconds, d["seconds"]
    row["area_change"] = out.to_trimesh().area / src.to_trimesh().area - 1.0
    taus = default_scales(src, 16)
    row["S_in"], row["S"] = total_complexity(src, taus, device=device), total_complexity(out, taus, device=device)
    m0 = _as_saved(out)
    taus0 = default_scales(m0, 16)
    t1 = time.perf_counter()
    m1, again = remesher(positions=wp.array(m0.local_vertices, dtype=wp.vec3, device=device))
    row["again"] = {"method": again.method, "why": again.why_level_set, "seconds": time.perf_counter() - t1,
                    "dS": total_complexity(m1, taus0, device=device) / total_complexity(m0, taus0, device=device) - 1.0}
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--meshes", default=os.path.join(_HERE, "..", "..", "shared", "data", "meshes"),
                    help="folder of the real meshes")
    ap.add_argument("--names", nargs="*", default=["sword.obj", "bunny.obj", "human_man.obj"])
    ap.add_argument("--faces", type=int, default=6000, help="face count (0: each input's)")
    ap.add_argument("--resolution", type=int, default=None, help="grid nodes along the longest side (default: auto)")
    ap.add_argument("--allow-changes", action="store_true", help="accept (and measure) a result that loses area")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    import vnc_warp._device  # noqa: F401  (quiet Warp first)
    from vnc_warp._device import get_device

    device = get_device(args.device)
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for name in args.names:
        row = first_remesh(os.path.join(args.meshes, name), args.faces or None, device, resolution=args.resolution,
                           allow_changes=args.allow_changes)
        rows.append(row)
        if "refused" in row:
            print(f"{name:20s} refused in {row['seconds']:.1f} s: {row['refused']}", flush=True)
        else:
            print(f"{name:20s} spacing {row['spacing']:.4g}  {row['method']:9s} dropped {100 * row['dropped_area']:.2f} % "
                  f"lost {100 * row['lost_area']:.2f} %  area {100 * row['area_change']:+.2f} %  S {row['S_in']:.3f} -> "
                  f"{row['S']:.3f}  one more remesh: {row['again']['method']}, S {100 * row['again']['dS']:+.3f} %  "
                  f"{row['seconds']:.1f} s" + (f"\n{'':20s} {row['grid_refined']}" if row["grid_refined"] else ""),
                  flush=True)
        with open(os.path.join(args.out, "first_remesh.json"), "w") as fh:
            json.dump({"device": str(device), "faces": args.faces, "resolution": args.resolution,
                       "allow_changes": args.allow_changes, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
