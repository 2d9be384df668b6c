"""VNC-Flow on real meshes: sphericity and t per stage, iterations and seconds, and the Fig. 7 comparison.

    python -m bench.flow_report --meshes ../shared/data/meshes --device cuda:0 --stages 32 --out flow_report
    python -m bench.flow_report --compare human_man.obj armadillo.obj --device cuda:0 --out fig7

Writes ``OUT/flow_report.json`` and ``OUT/flow_report.md`` (a table per mesh: stage, t, ideal 1 - i/N,
iterations, seconds, sphericity, status) and, with ``--compare``, the same numbers for VNC-Flow, the
fixed-scale variants and explicit/implicit mean curvature flow (Fig. 7). ``--max-minutes`` stops starting new
runs once the budget is spent, so a GPU session ends on time; what finished is written.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import numpy as np

DEFAULT_MESHES = ["spot.obj", "bunny.obj", "armadillo.obj", "human_man.obj", "faust_tr_reg_025.ply", "fandisk.obj",
                  "torus.obj"]
VARIANTS = {
    "vnc_adaptive": {},
    "fixed_small": {"scale_mode": "small"},
    "fixed_large": {"scale_mode": "large"},
    "mcf_explicit": {"method": "mcf_explicit"},
    "mcf_implicit": {"method": "mcf_implicit"},
}


def _run(path, variant, params, args):
    from vnc_warp.flow import flow

    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj = flow(path, stages=args.stages, faces=args.faces, device=args.device, progress=False,
                    max_iters=args.max_iters, **params)
    stages = [{k: r[k] for k in ("index", "t", "iterations", "seconds", "sphericity", "euler", "status", "vertices", "faces")}
              for r in traj.records]
    return {"mesh": os.path.basename(path), "variant": variant, "stages": stages, "seconds": time.perf_counter() - t0,
            "final_t": float(traj.t[-1]), "final_sphericity": traj.records[-1]["sphericity"],
            "input_sphericity": traj.records[0]["sphericity"], "warnings": len(caught)}


def _table(run, n) -> str:
    lines = [f"### {run['mesh']} — {run['variant']} ({run['seconds']:.1f} s, sphericity "
             f"{run['input_sphericity']:.3f} -> {run['final_sphericity']:.3f})", "",
             "| stage | t | ideal 1-i/N | iterations | seconds | sphericity | Euler | status |",
             "|---|---|---|---|---|---|---|---|"]
    for r in run["stages"]:
        lines.append(f"| {r['index']} | {r['t']:.3f} | {1 - r['index'] / n:.3f} | {r['iterations']} | "
                     f"{r['seconds']:.2f} | {r['sphericity']:.3f} | {r.get('euler', '')} | {r['status']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--meshes", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "meshes"),
                   help="folder of the real meshes")
    p.add_argument("--names", nargs="*", default=DEFAULT_MESHES, help="meshes to flow with VNC-Flow")
    p.add_argument("--compare", nargs="*", default=[], help="meshes for the Fig. 7 comparison (all variants)")
    p.add_argument("--stages", type=int, default=32)
    p.add_argument("--faces", type=int, default=None, help="face count (default: each input's)")
    p.add_argument("--max-iters", type=int, default=300)
    p.add_argument("--device", default=None)
    p.add_argument("--max-minutes", type=float, default=9.0, help="start no new run after this")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)

    import warp as wp

    import vnc_warp
    from vnc_warp._device import get_device

    dev = get_device(args.device)
    os.makedirs(args.out, exist_ok=True)
    jobs = [(n, "vnc_adaptive") for n in (args.names if not args.compare else [])]
    jobs += [(n, v) for n in args.compare for v in VARIANTS]
    report = {"device": dev.name if hasattr(dev, "name") else str(dev), "device_alias": str(dev),
              "warp": wp.__version__, "vnc_warp": vnc_warp.__version__, "python": platform.python_version(),
              "stages": args.stages, "faces": args.faces, "runs": [], "skipped": []}
    start = time.perf_counter()
    for name, variant in jobs:
        if time.perf_counter() - start > 60 * args.max_minutes:
            report["skipped"].append({"mesh": name, "variant": variant, "why": "time budget"})
            continue
        try:
            run = _run(os.path.join(args.meshes, name), variant, VARIANTS[variant], args)
        except Exception as exc:  # a failing run is reported, the others still run
            report["runs"].append({"mesh": name, "variant": variant, "error": f"{type(exc).__name__}: {exc}"})
            continue
        report["runs"].append(run)
        print(f"{name:24s} {variant:14s} {run['seconds']:7.1f} s  t_final {run['final_t']:.3f}  "
              f"sphericity {run['input_sphericity']:.3f} -> {run['final_sphericity']:.3f}", flush=True)
        with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
            json.dump(report, fh, indent=1)
    summary = ["| mesh | variant | seconds | final t | sphericity in -> out | stages meeting budget |",
               "|---|---|---|---|---|---|"]
    for r in report["runs"]:
        if "error" in r:
            summary.append(f"| {r['mesh']} | {r['variant']} | error: {r['error']} | | | |")
            continue
        met = sum(s["status"] == "budget" for s in r["stages"][1:])
        summary.append(f"| {r['mesh']} | {r['variant']} | {r['seconds']:.1f} | {r['final_t']:.3f} | "
                       f"{r['input_sphericity']:.3f} -> {r['final_sphericity']:.3f} | {met}/{len(r['stages']) - 1} |")
    body = [f"Device: {report['device']}; stages {args.stages}; warp {report['warp']}", "", *summary, ""]
    body += [_table(r, args.stages) + "\n" for r in report["runs"] if "error" not in r]
    with open(os.path.join(args.out, "flow_report.md"), "w") as fh:
        fh.write("\n".join(body))
    with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
        json.dump(report, fh, indent=1)
    print("\n".join(summary))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
