"""``vnc-warp flow``: run VNC-Flow on one mesh, writing each stage as it finishes (resumable)."""

from __future__ import annotations

import json

HELP = "VNC-Flow (Algorithm 1): a mesh -> N+1 (mesh, t) stages in OUT (resumes an interrupted run)"


def add_flow_options(p) -> None:
    """Options shared by ``flow`` and ``flow-batch``."""
    p.add_argument("--stages", type=int, default=32, help="number of stages N")
    p.add_argument("--faces", type=int, default=None, help="face count of every state (default: the input's)")
    p.add_argument("--device", default=None, help="Warp device (cpu, cuda:0); default: CUDA when present")
    p.add_argument("--method", choices=["vnc", "mcf_explicit", "mcf_implicit"], default="vnc",
                   help="VNC-Flow (Eq. 5) or a classical mean-curvature-flow baseline (Fig. 7)")
    p.add_argument("--scale-mode", choices=["adaptive", "small", "large"], default="adaptive",
                   help="adaptive scales (Eq. 6) or a fixed small/large scale (Fig. 7 ablations)")
    p.add_argument("--max-iters", type=int, default=300, help="iteration cap per stage")
    p.add_argument("--step-fraction", type=float, default=0.25, help="eta: per-iteration move in mean edge lengths")
    p.add_argument("--substage-budget", type=float, default=None,
                   help="largest share of S_init flowed between two remeshes (default 1/32: a stage of budget 1/N is "
                        "flowed in ceil(32/N) sub-stages; 1/N flows each stage in one)")
    p.add_argument("--no-remesh", action="store_true", help="skip SDF remeshing (input must be watertight)")
    p.add_argument("--allow-changes", action="store_true",
                   help="accept a first remesh that drops components or loses parts thinner than its grid")


def flow_kwargs(args) -> dict:
    """:func:`vnc_warp.flow.flow` keyword arguments from the options of :func:`add_flow_options`."""
    kw = dict(stages=args.stages, faces=args.faces, device=args.device, method=args.method,
              scale_mode=args.scale_mode, max_iters=args.max_iters, step_fraction=args.step_fraction,
              remesh=not args.no_remesh, allow_changes=args.allow_changes, progress=not args.no_progress)
    if args.substage_budget is not None:
        kw["substage_budget"] = args.substage_budget
    return kw


def add_arguments(p) -> None:
    p.add_argument("mesh", help="input mesh (any format trimesh reads)")
    p.add_argument("--out", required=True, help="output folder: stage_XXX.ply + manifest.json")
    add_flow_options(p)


def run(args) -> int:
    from vnc_warp.flow import flow

    try:
        traj = flow(args.mesh, out_dir=args.out, **flow_kwargs(args))
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"the finished stages are kept in {args.out}; run the same command again to "
                                "resume") from None
    last = traj.records[-1]
    print(json.dumps({"out": args.out, "stages": len(traj.meshes) - 1, "t": [round(float(t), 4) for t in traj.t],
                      "final_sphericity": last["sphericity"], "seconds": sum(r["seconds"] for r in traj.records)}))
    return 0
