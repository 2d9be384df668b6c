"""Does VNC-Flow repeat itself bit for bit? Two runs of the same flow on each mesh, compared stage by stage.

    python -m bench.determinism --meshes ../shared/data/meshes/bunny.obj ../shared/data/meshes/faust_tr_reg_025.ply \\
        ../shared/data/meshes/human_man.obj --stages 8 --device cuda --out OUT
    python -m bench.determinism --meshes ../shared/data/meshes/spot_lowres.obj --stages 4 --device cpu --out OUT

For every mesh it runs ``vnc_warp.flow`` twice with the same arguments on one device and reports, over the recorded
stages: the largest ``|t_i^(1) - t_i^(2)|``, the first stage whose vertices or faces differ in any bit (``-`` when
none does), the largest vertex distance between the runs at stages of equal face count, and whether every stage is
bit-identical. On the CPU Warp runs each kernel on one thread, so two runs there must be identical; on CUDA they are
identical only if nothing between two stages adds floats in the order threads happen to finish.

``--meshes`` takes files or folders (a folder: its ``.obj``, ``.ply``, ``.off``, ``.stl`` files); ``--faces`` sets
the remeshed face count (default: the input's, capped by ``--max-faces``). Prints a table and writes
``OUT/determinism.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

_SUFFIXES = (".obj", ".ply", ".off", ".stl")


def _mesh_paths(items: list[str]) -> list[str]:
    paths = []
    for item in items:
        if os.path.isdir(item):
            paths += sorted(os.path.join(item, f) for f in os.listdir(item) if f.lower().endswith(_SUFFIXES))
        elif os.path.isfile(item):
            paths.append(item)
        else:
            raise SystemExit(f"determinism: {item}: no such file or folder")
    return paths


def compare(a, b) -> dict:
    """Stage-by-stage comparison of two trajectories ``a`` and ``b`` of the same input.

    Returns:
        A dict: ``stages`` compared (the shorter length), ``max_dt`` (largest |t| difference), ``first_diff``
        (first stage index whose faces or vertex bits differ, None when none), ``max_dx`` (largest vertex distance
        over stages of equal shape, in mesh units), ``identical`` (every stage bit for bit, and equal lengths).
    """
    n = min(len(a.meshes), len(b.meshes))
    t_a, t_b = np.asarray(a.t[:n], dtype=np.float64), np.asarray(b.t[:n], dtype=np.float64)
    first, max_dx = None, 0.0
    for i in range(n):
        ma, mb = a.meshes[i], b.meshes[i]
        va, vb = np.asarray(ma.vertices), np.asarray(mb.vertices)
        fa, fb = np.asarray(ma.faces), np.asarray(mb.faces)
        same_shape = va.shape == vb.shape and fa.shape == fb.shape
        if same_shape:
            max_dx = max(max_dx, float(np.max(np.linalg.norm(va.astype(np.float64) - vb, axis=1), initial=0.0)))
        if first is None and not (same_shape and np.array_equal(fa, fb) and va.tobytes() == vb.tobytes()):
            first = i
    return {"stages": n, "max_dt": float(np.max(np.abs(t_a - t_b), initial=0.0)), "first_diff": first,
            "max_dx": max_dx, "identical": first is None and len(a.meshes) == len(b.meshes)}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--meshes", nargs="+", required=True, help="mesh files or folders")
    parser.add_argument("--stages", type=int, default=8)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--faces", type=int, default=None, help="remeshed face count (default: the input's)")
    parser.add_argument("--max-faces", type=int, default=None, help="cap on the default face count")
    parser.add_argument("--out", required=True, help="output folder (created)")
    args = parser.parse_args(argv)

    import warp as wp

    from vnc_warp import flow
    from vnc_warp.mesh import load_mesh

    wp.config.quiet = True
    os.makedirs(args.out, exist_ok=True)
    rows = []
    for path in _mesh_paths(args.meshes):
        faces = args.faces
        if faces is None and args.max_faces:
            faces = min(load_mesh(path).num_faces, args.max_faces)
        seconds, runs, errors = [], [], []
        for _ in range(2):
            start = time.perf_counter()
            try:
                runs.append(flow(path, stages=args.stages, faces=faces, device=args.device, progress=False))
            except Exception as exc:  # a failed flow is a result too: do both runs fail alike?
                errors.append(f"{type(exc).__name__}: {exc}")
            seconds.append(time.perf_counter() - start)
        if errors:
            same = len(errors) == 2 and errors[0] == errors[1]
            row = {"mesh": os.path.basename(path), "faces": faces or 0, "seconds": seconds, "stages": 0,
                   "identical": same, "first_diff": None if same else 0, "max_dt": float("nan"),
                   "max_dx": float("nan"), "errors": errors}
            print(f"{row['mesh']}: {len(errors)} of 2 runs failed{' alike' if same else ''}: {errors[0][:300]}",
                  flush=True)
            rows.append(row)
            continue
        row = {"mesh": os.path.basename(path), "faces": runs[0].meshes[0].num_faces, "seconds": seconds,
               **compare(*runs)}
        rows.append(row)
        print(f"{row['mesh']}: identical={row['identical']} max|dt|={row['max_dt']:.3g} "
              f"first differing stage={row['first_diff']} ({seconds[0]:.1f} s, {seconds[1]:.1f} s)", flush=True)

    header = "| mesh | faces | states (stage 0..N) | identical | first differing stage | max \\|dt\\| | max \\|dx\\| | seconds |"
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        first = "-" if r["first_diff"] is None else str(r["first_diff"])
        lines.append(f"| {r['mesh']} | {r['faces']:,} | {r['stages']} | {'yes' if r['identical'] else 'NO'} | {first} "
                     f"| {r['max_dt']:.3g} | {r['max_dx']:.3g} | {r['seconds'][0]:.1f} + {r['seconds'][1]:.1f} |")
    print("\n".join(lines))
    report = {"device": str(wp.get_device(args.device)), "platform": platform.platform(), "stages": args.stages,
              "warp": wp.config.version, "runs": rows}
    with open(os.path.join(args.out, "determinism.json"), "w") as fh:
        json.dump(report, fh, indent=2)
    return 0 if all(r["identical"] for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
