"""VNC-Flow on the real meshes: how well each trajectory keeps its budgets, and where the seconds go.

    python -m bench.flow_report --meshes ../shared/data/meshes --all --stages 32 --device cuda:0 --out OUT
    python -m bench.flow_report --names human_man.obj bunny.obj --stages 8 --max-faces 3000 --device cpu --out OUT
    python -m bench.flow_report --compare human_man.obj armadillo.obj --device cuda:0 --out fig7

For every mesh (``--all``: every closed mesh in the folder; ``--names``: those) it runs VNC-Flow and measures

* **t control**: the largest ``|t_i - (1 - i/N)|`` over the recorded stages, over all of them and over those that
  are not a documented exception (the last stage; a stage whose remesh changed the topology), and whether any
  two consecutive stages hold the same mesh;
* **thinning**: the smallest stage-to-stage ratio of the 5th-percentile relative thickness (4096 area-weighted
  rays along inward normals, over the radius of the sphere of equal area);
* **remesh alone**: the change of the total VNC-AUC ``S`` (16 scales of stage 0) when stage 0 is remeshed once
  more with the trajectory's remesher and nothing else happens;
* **seconds**: wall seconds of the whole flow (stage 0's remesh included), and the part breakdown summed over
  stages: remesh (input, SDF, marching cubes, components, decimation, regularization, checks) and stages (setup:
  adaptive scales and thickness budgets; steps; S evaluations; record).

Writes ``OUT/flow_report.json`` (every stage record) and ``OUT/flow_report.md`` (the summary table, tuned and
held-out meshes apart, and the part breakdown). ``--compare`` runs VNC-Flow, the fixed-scale variants and
explicit/implicit mean curvature flow instead (Fig. 7). ``--max-minutes`` stops starting new runs once the
budget is spent, so a GPU session ends on time; what finished is written.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import numpy as np

# The meshes the flow's rule constants were tuned on (thin_fraction, tolerance, the remesher's agreement
# thresholds); every other closed mesh is held out and reported apart.
TUNED = ("human_man.obj", "spot_lowres.obj", "bunny.obj", "torus.obj", "wingnut.obj", "fandisk.obj")
VARIANTS = {
    "vnc_adaptive": {},
    "fixed_small": {"scale_mode": "small"},
    "fixed_large": {"scale_mode": "large"},
    "mcf_explicit": {"method": "mcf_explicit"},
    "mcf_implicit": {"method": "mcf_implicit"},
}
REMESH_PARTS = ("input", "sdf", "marching_cubes", "components", "decimation", "regularize", "checks")
STAGE_PARTS = ("setup", "steps", "evaluations", "record")


def closed_meshes(folder: str) -> list[str]:
    """Mesh files in ``folder`` that load as watertight surfaces, by name."""
    import vnc_warp as vw

    out = []
    for name in sorted(os.listdir(folder)):
        if os.path.splitext(name)[1].lower() not in (".obj", ".ply", ".off", ".stl"):
            continue
        try:
            if vw.load_mesh(os.path.join(folder, name)).is_watertight:
                out.append(name)
        except ValueError:
            continue
    return out


def _exception(rec: dict, n: int) -> str | None:
    """Which documented exception a stage record is, if any."""
    if rec["index"] == n:
        return "last stage"
    rm = rec.get("remesh") or {}
    if rm and rm.get("euler") != rm.get("euler_in"):
        return "topology change"
    return None


def summarize(traj, n: int) -> dict:
    """t control, thinning and same-mesh facts of a trajectory."""
    recs = traj.records
    dev = [abs(r["t"] - (1.0 - r["index"] / n)) for r in recs[1:]]
    ruled = [abs(r["t"] - (1.0 - r["index"] / n)) for r in recs[1:] if _exception(r, n) is None]
    ratios = [r["thickness_ratio"] for r in recs[1:] if r.get("thickness_ratio")]
    same = [i for i, (m, prev) in enumerate(zip(traj.meshes[1:], traj.meshes[:-1]), start=1)
            if m.num_vertices == prev.num_vertices and np.array_equal(m.vertices, prev.vertices)]
    return {"max_dt": max(dev, default=0.0), "max_dt_ruled": max(ruled, default=0.0),
            "exceptions": {r["index"]: _exception(r, n) for r in recs[1:] if _exception(r, n)},
            "min_thickness_ratio": min(ratios, default=None), "thickness": [r["thickness"] for r in recs],
            "same_mesh_stages": same, "final_t": float(traj.t[-1]),
            "statuses": {s: sum(r["status"] == s for r in recs[1:]) for s in {r["status"] for r in recs[1:]}}}


def parts(traj) -> dict:
    """Seconds per part summed over the trajectory's records."""
    out = {f"remesh.{k}": 0.0 for k in REMESH_PARTS}
    out.update({f"stage.{k}": 0.0 for k in STAGE_PARTS})
    for r in traj.records:
        for k, v in ((r.get("remesh") or {}).get("seconds") or {}).items():
            out[f"remesh.{k}"] = out.get(f"remesh.{k}", 0.0) + v
        for k, v in (r.get("parts") or {}).items():
            out[f"stage.{k}"] = out.get(f"stage.{k}", 0.0) + v
    return out


def remesh_alone(traj, device) -> dict:
    """``S`` before and after remeshing stage 0 once more with the trajectory's remesher settings."""
    import warp as wp

    from vnc_warp.flow import total_complexity
    from vnc_warp.remesh import _Remesher

    p = traj.info["params"]
    m0 = traj.meshes[0]
    taus = np.asarray(traj.info["taus"])
    remesher = _Remesher(faces=p["faces"], resolution=p["resolution"], device=device, warn=False)
    remesher.adopt(m0, traj.info["remesh_spacing"], traj.info["source"])
    t0 = time.perf_counter()
    m1, report = remesher(positions=wp.array(m0.vertices, dtype=wp.vec3, device=device))
    seconds = time.perf_counter() - t0
    S0, S1 = traj.info["S_init"], total_complexity(m1, taus, kappa=p["kappa"], device=device)
    return {"dS": S1 / S0 - 1.0, "method": report.method, "why": report.why_level_set, "seconds": seconds,
            "parts": report.seconds}


def _run(path, variant, params, args):
    from vnc_warp.flow import flow
    from vnc_warp.mesh import load_mesh

    faces = args.faces
    if faces is None and args.max_faces:
        faces = min(load_mesh(path).num_faces, args.max_faces)
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj = flow(path, stages=args.stages, faces=faces, device=args.device, progress=False,
                    max_iters=args.max_iters, **params)
    seconds = time.perf_counter() - t0
    keep = ("index", "t", "target_t", "iterations", "evaluations", "seconds", "sphericity", "thickness",
            "thickness_ratio", "euler", "status", "exception", "vertices", "faces")
    stages = [{k: r.get(k) for k in keep} | {"remesh": (r.get("remesh") or {}).get("method")} for r in traj.records]
    name = os.path.basename(path)
    run = {"mesh": name, "variant": variant, "held_out": name not in TUNED, "faces": traj.meshes[0].num_faces,
           "seconds": seconds, "stages": stages, "final_t": float(traj.t[-1]),
           "input_sphericity": traj.records[0]["sphericity"], "final_sphericity": traj.records[-1]["sphericity"],
           "warnings": [str(w.message) for w in caught], "parts": parts(traj)}
    if variant == "vnc_adaptive":
        run.update(summarize(traj, args.stages))
        if traj.info["params"]["remesh"]:
            run["remesh_alone"] = remesh_alone(traj, args.device)
    return run


def _fmt(x, spec=".3f"):
    return "" if x is None else format(x, spec)


def summary_table(runs: list, title: str) -> list[str]:
    lines = [f"#### {title}", "",
             "| mesh | faces | max \\|t_i - (1 - i/N)\\| (exceptions out) | all stages | exceptions | smallest "
             "thickness ratio | S change, one remesh | seconds | remesh s | stage s | final t |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        if "error" in r:
            lines.append(f"| {r['mesh']} | | error: {r['error']} | | | | | | | | |")
            continue
        p = r["parts"]
        rem = sum(v for k, v in p.items() if k.startswith("remesh."))
        stg = sum(v for k, v in p.items() if k.startswith("stage."))
        exc = ", ".join(f"{i}: {e}" for i, e in r["exceptions"].items())
        ra = r.get("remesh_alone") or {}
        lines.append(f"| {r['mesh']} | {r['faces']:,} | {_fmt(r['max_dt_ruled'])} | {_fmt(r['max_dt'])} | {exc} | "
                     f"{_fmt(r['min_thickness_ratio'])} | {_fmt(100 * ra['dS'], '+.2f') + ' %' if ra else ''} | "
                     f"{r['seconds']:.1f} | {rem:.1f} | {stg:.1f} | {r['final_t']:.3f} |")
    return lines


def parts_table(runs: list) -> list[str]:
    keys = [f"remesh.{k}" for k in REMESH_PARTS] + [f"stage.{k}" for k in STAGE_PARTS]
    lines = ["| mesh | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in runs:
        if "error" not in r:
            lines.append(f"| {r['mesh']} | " + " | ".join(f"{r['parts'].get(k, 0.0):.2f}" for k in keys) + " |")
    return lines


def stage_table(run: dict, n: int) -> str:
    lines = [f"### {run['mesh']} — {run['variant']} ({run['seconds']:.1f} s, sphericity "
             f"{run['input_sphericity']:.3f} -> {run['final_sphericity']:.3f})", "",
             "| stage | t | ideal 1-i/N | iterations | evaluations | seconds | sphericity | thickness | ratio | Euler | "
             "remesh | status |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in run["stages"]:
        lines.append(f"| {r['index']} | {r['t']:.3f} | {1 - r['index'] / n:.3f} | {r['iterations']} | "
                     f"{r.get('evaluations') or ''} | {r['seconds']:.2f} | {r['sphericity']:.3f} | "
                     f"{_fmt(r.get('thickness'))} | {_fmt(r.get('thickness_ratio'))} | {r.get('euler', '')} | "
                     f"{r.get('remesh') or ''} | {r['status']} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("--meshes", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "meshes"),
                   help="folder of the real meshes")
    p.add_argument("--all", action="store_true", help="every closed mesh in --meshes")
    p.add_argument("--names", nargs="*", default=["human_man.obj", "faust_tr_reg_025.ply"],
                   help="meshes to flow with VNC-Flow (without --all)")
    p.add_argument("--compare", nargs="*", default=[], help="meshes for the Fig. 7 comparison (all variants)")
    p.add_argument("--stages", type=int, default=32)
    p.add_argument("--faces", type=int, default=None, help="face count of every run (default: each input's)")
    p.add_argument("--max-faces", type=int, default=50_000,
                   help="cap on each input's face count (the paper's 50k); 0: no cap")
    p.add_argument("--max-iters", type=int, default=300)
    p.add_argument("--device", default=None)
    p.add_argument("--max-minutes", type=float, default=9.0, help="start no new run after this")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)

    import warp as wp

    import vnc_warp
    from vnc_warp._device import get_device

    dev = get_device(args.device)
    args.device = str(dev)
    os.makedirs(args.out, exist_ok=True)
    names = closed_meshes(args.meshes) if args.all else list(args.names)
    jobs = [(n, "vnc_adaptive") for n in (names if not args.compare else [])]
    jobs += [(n, v) for n in args.compare for v in VARIANTS]
    report = {"device": dev.name if hasattr(dev, "name") else str(dev), "device_alias": str(dev),
              "warp": wp.__version__, "vnc_warp": vnc_warp.__version__, "python": platform.python_version(),
              "stages": args.stages, "faces": args.faces, "max_faces": args.max_faces, "tuned": list(TUNED),
              "command": "python -m bench.flow_report " + " ".join(argv if argv is not None else os.sys.argv[1:]),
              "runs": [], "skipped": []}
    start = time.perf_counter()
    for name, variant in jobs:
        if time.perf_counter() - start > 60 * args.max_minutes:
            report["skipped"].append({"mesh": name, "variant": variant, "why": "time budget"})
            continue
        try:
            run = _run(os.path.join(args.meshes, name), variant, VARIANTS[variant], args)
        except Exception as exc:  # a failing run is reported, the others still run
            report["runs"].append({"mesh": name, "variant": variant, "error": f"{type(exc).__name__}: {exc}"})
            print(f"{name:24s} {variant:14s} error: {type(exc).__name__}: {exc}", flush=True)
            continue
        report["runs"].append(run)
        extra = ""
        if variant == "vnc_adaptive":
            extra = (f"  max|dt| {run['max_dt_ruled']:.3f} (all {run['max_dt']:.3f})  thickness ratio "
                     f"{_fmt(run['min_thickness_ratio'])}  remesh alone "
                     f"{100 * run['remesh_alone']['dS']:+.2f} %" if "remesh_alone" in run else "")
        print(f"{name:24s} {variant:14s} {run['seconds']:7.1f} s  t_final {run['final_t']:.3f}{extra}", flush=True)
        with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
            json.dump(report, fh, indent=1)
    flows = [r for r in report["runs"] if r["variant"] == "vnc_adaptive"]
    body = [f"Device: {report['device']}; stages {args.stages}; faces: each input's, at most {args.max_faces:,}; "
            f"warp {report['warp']}; command: `{report['command']}`", ""]
    if flows:
        body += summary_table([r for r in flows if not r.get("held_out")], "Meshes the rule constants were tuned on")
        body += [""] + summary_table([r for r in flows if r.get("held_out")], "Held-out meshes") + [""]
        body += ["#### Seconds per part (summed over the stages)", ""] + parts_table(flows) + [""]
    others = [r for r in report["runs"] if r["variant"] != "vnc_adaptive" and "error" not in r]
    if others:
        body += ["| mesh | variant | seconds | final t | sphericity in -> out |", "|---|---|---|---|---|"]
        body += [f"| {r['mesh']} | {r['variant']} | {r['seconds']:.1f} | {r['final_t']:.3f} | "
                 f"{r['input_sphericity']:.3f} -> {r['final_sphericity']:.3f} |" for r in others] + [""]
    body += [stage_table(r, args.stages) + "\n" for r in report["runs"] if "error" not in r]
    with open(os.path.join(args.out, "flow_report.md"), "w") as fh:
        fh.write("\n".join(body))
    with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
        json.dump(report, fh, indent=1)
    print("\n".join(body[:2 + 2 * (len(flows) + 8)]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
