"""``vnc-warp curvature``: per-vertex VNC of a mesh across scales, to a coloured PLY and a NumPy archive."""

from __future__ import annotations

import json
import os
import time

import numpy as np

HELP = "VNC curvature (Eq. 2/3) of a mesh at one or more scales: coloured PLY + .npz"


def add_arguments(p) -> None:
    p.add_argument("mesh", nargs="?", default=None, help="input mesh (any format trimesh reads); default: the bundled Spot")
    p.add_argument("--out", required=True, help="output path; writes OUT.ply (coloured) and OUT.npz (drops any extension)")
    p.add_argument("--tau", type=float, nargs="+", default=None,
                   help="scales in mesh units (default: 16 scales from 2 mean edge lengths to 1/4 of the bbox diagonal)")
    p.add_argument("--tau-edges", type=float, nargs="+", default=None,
                   help="scales in multiples of the mean edge length (instead of --tau)")
    p.add_argument("--variant", choices=["soft", "hard"], default="soft", help="VNC-soft (Eq. 3) or VNC-hard (Eq. 2)")
    p.add_argument("--kappa", type=float, default=6.0, help="cut-off ratio r = kappa * sigma")
    p.add_argument("--color-scale", type=int, default=0, help="index of the scale whose values colour the PLY")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: CUDA when present")


def run(args) -> int:
    import vnc_warp as vw
    from vnc_warp._files import output_dir
    from vnc_warp.data import mesh_path
    from vnc_warp.render import colormap

    base = os.path.splitext(args.out)[0]
    output_dir(os.path.dirname(os.path.abspath(base)), what=f"--out {args.out}: folder")
    args.mesh = str(args.mesh or mesh_path("spot"))
    mesh = vw.load_mesh(args.mesh)
    if args.tau is not None and args.tau_edges is not None:
        raise ValueError("give --tau or --tau-edges, not both")
    if args.tau_edges is not None:
        taus = np.asarray(sorted(args.tau_edges), dtype=np.float64) * mesh.mean_edge_length
    elif args.tau is not None:
        taus = np.asarray(sorted(args.tau), dtype=np.float64)
    else:
        taus = vw.default_scales(mesh)
    if not 0 <= args.color_scale < taus.size:
        raise ValueError(f"--color-scale must index one of the {taus.size} scales")
    t0 = time.perf_counter()
    if taus.size == 1:
        op = vw.vnc_soft if args.variant == "soft" else vw.vnc_hard
        H, n = op(mesh, float(taus[0]), kappa=args.kappa, device=args.device)
        H_all, normals, auc = H.numpy()[None], n.numpy(), None
    else:
        curve = vw.scale_curve(mesh, taus, args.variant, kappa=args.kappa, device=args.device)
        H_all, auc = curve.H.numpy(), vw.vnc_auc(curve).numpy()
        op = vw.vnc_soft if args.variant == "soft" else vw.vnc_hard
        normals = op(mesh, float(taus[args.color_scale]), kappa=args.kappa, device=args.device)[1].numpy()
    seconds = time.perf_counter() - t0
    h = H_all[args.color_scale]
    lim = float(np.quantile(np.abs(h - np.median(h)), 0.98)) or 1.0
    rgb = colormap(h, "coolwarm", vmin=float(np.median(h)) - lim, vmax=float(np.median(h)) + lim)
    mesh.save(base + ".ply", vertex_colors=(np.clip(rgb, 0, 1) * 255).astype(np.uint8))
    np.savez(base + ".npz", H=H_all, taus=taus, normals=normals, vertices=mesh.vertices, faces=mesh.faces,
             **({} if auc is None else {"auc": auc}))
    summary = {"mesh": args.mesh, "vertices": mesh.num_vertices, "faces": mesh.num_faces, "variant": args.variant,
               "kappa": args.kappa, "taus": taus.tolist(), "mean_curve": H_all.mean(1).tolist(),
               "seconds": seconds, "outputs": [base + ".ply", base + ".npz"]}
    print(json.dumps(summary, indent=1))
    return 0
