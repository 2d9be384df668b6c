"""VNC-Flow on the real meshes: how well each trajectory keeps its budgets, and where the seconds go.

    python -m bench.flow_report --meshes ../shared/data/meshes --all --stages 32 --device cuda --max-minutes 7 --out OUT
    python -m bench.flow_report --names human_man.obj bunny.obj --stages 8 --max-faces 3000 --device cpu --out OUT
    python -m bench.flow_report --compare human_man.obj armadillo.obj --device cuda:0 --out fig7

For every mesh (``--all``: every closed mesh in the folder; ``--names``: those) it runs VNC-Flow and measures

* **t control**: the largest ``|t_i - (1 - i/N)|`` over the recorded stages, over all of them and over those that
  are not a documented exception (the last stage; a stage whose remesh changed the topology), and which stages
  hold the previous stage's state (its very vertices, or no step of Eq. (5) taken: its re-tessellation);
* **thinning**: the smallest stage-to-stage ratio of the 5th-percentile relative thickness (4096 area-weighted
  rays along inward normals, over the radius of the sphere of equal area), and of the thinnest part's
  (``vnc_warp.flow.thinnest_part``: the smallest 1-ring median of the thickness along inward vertex normals, over
  the same radius), which sees a stalk or a thread that carries too little area for the 5th percentile;
* **remesh alone**: the change of the total VNC-AUC ``S`` (16 scales of stage 0) when stage 0 is remeshed once
  more with the trajectory's remesher and nothing else happens;
* **seconds**: wall seconds of the whole flow (stage 0's remesh included; kernel compilation and the device's
  context are paid by a warm-up flow of a small sphere before the first mesh, reported apart), and the part
  breakdown summed over stages: remeshes between stages (input, SDF, marching cubes, components, decimation,
  regularization, checks), remeshes within stages (how many, and the same parts) and stages (setup: adaptive
  scales and thickness budgets; steps; S evaluations; contact checks; remeshes within, all told; record).

Writes ``OUT/flow_report.json`` (every stage record) and ``OUT/flow_report.md`` (the summary table, tuned and
held-out meshes apart, and the part breakdown: ready to paste into the README), and for human_man and FAUST 025
(run first) their trajectories under ``OUT/trajectories`` and filmstrips ``OUT/filmstrip_<mesh>.png``.
``--compare`` runs VNC-Flow, the fixed-scale variants and explicit/implicit mean curvature flow instead (Fig. 7).
``--max-minutes``: a mesh is skipped (and listed as skipped) when the slowest run so far, per face, says it would
end after the budget, so one GPU session ends on time; what finished is written after every run.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
import warnings

import numpy as np

# The meshes the flow's rule constants (tube_rho, ball_rho, tolerance) and the remesher's agreement thresholds
# were tuned or diagnosed on; every other closed mesh is held out and reported apart.
TUNED = ("human_man.obj", "faust_tr_reg_025.ply", "spot_lowres.obj", "bunny.obj", "torus.obj", "wingnut.obj",
         "fandisk.obj", "springer.obj", "penguin.obj")
# Run first (a time budget skips the last meshes, never these), with filmstrips under --out.
BODIES = ("human_man.obj", "faust_tr_reg_025.ply")
VARIANTS = {
    "vnc_adaptive": {},
    "fixed_small": {"scale_mode": "small"},
    "fixed_large": {"scale_mode": "large"},
    "mcf_explicit": {"method": "mcf_explicit"},
    "mcf_implicit": {"method": "mcf_implicit"},
}
REMESH_PARTS = ("input", "sdf", "marching_cubes", "components", "decimation", "regularize", "checks")
# stage.checks: the contact check of each evaluation; stage.remesh: the remeshes within stages, all told
STAGE_PARTS = ("setup", "steps", "evaluations", "checks", "remesh", "record")


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


def _moves(rec: dict, S_init: float) -> dict:
    """Where a stage's ``t`` went: ``t_start``, ``t`` after the remesh between stages (the first entry of the
    stage's S history), the remeshes within the stage (path, Euler characteristic before and after) and the S
    history as ``[iteration, t]`` pairs: a stage that lands below its window after a within-stage join, or starts
    below it after a level-set remesh, shows which remesh took ``t`` there."""
    history = rec.get("history") or []
    return {"t_start": history[0][1] / S_init if history else None,
            "within": [[w.get("method"), w.get("euler_in"), w.get("euler")] for w in rec.get("remeshes_within") or []],
            "history_t": [[it, S / S_init] for it, S in history]}


def summarize(traj, n: int) -> dict:
    """t control, thinning and same-mesh facts of a trajectory."""
    from vnc_warp.trajectory import budget_summary

    recs = traj.records
    budgets = budget_summary(recs, n)
    ratios = [r["thickness_ratio"] for r in recs[1:] if r.get("thickness_ratio")]
    thinnest = [r["thinnest_ratio"] for r in recs[1:] if r.get("thinnest_ratio")]
    # a stage holds the previous stage's state when its vertices are that state's, or when it took no step of
    # Eq. (5): then it is that state re-tessellated by the remesh between stages, new vertices, the same shape
    same = [i for i, (m, prev, r) in enumerate(zip(traj.meshes[1:], traj.meshes[:-1], recs[1:]), start=1)
            if (r.get("iterations") == 0 and not r.get("bridge") and not r.get("from_bridge"))
            or (m.num_vertices == prev.num_vertices and np.array_equal(m.vertices, prev.vertices))]
    return {"max_dt": budgets["max_dt"], "max_dt_ruled": budgets["max_dt_ruled"], "exceptions": budgets["exceptions"],
            "min_thickness_ratio": min(ratios, default=None), "thickness": [r["thickness"] for r in recs],
            "min_thinnest_ratio": min(thinnest, default=None), "thinnest": [r.get("thinnest") for r in recs],
            "same_mesh_stages": same, "final_t": float(traj.t[-1]),
            "statuses": {s: sum(r["status"] == s for r in recs[1:]) for s in {r["status"] for r in recs[1:]}}}


def parts(traj) -> dict:
    """Seconds per part summed over the trajectory's records: ``remesh.*`` the remeshes between stages (stage 0's
    first remesh of the input included), ``within.*`` the remeshes within stages (contact joins, stalls; ``within.n``
    counts them), ``stage.*`` the stages' own parts (``stage.remesh`` is the whole of each remesh within a stage:
    ``within.*`` and setting the flow up again on its result)."""
    out = {f"remesh.{k}": 0.0 for k in REMESH_PARTS}
    out.update({f"within.{k}": 0.0 for k in REMESH_PARTS})
    out["within.n"] = 0
    out.update({f"stage.{k}": 0.0 for k in STAGE_PARTS})
    for r in traj.records:
        for k, v in ((r.get("remesh") or {}).get("seconds") or {}).items():
            out[f"remesh.{k}"] = out.get(f"remesh.{k}", 0.0) + v
        for rm in r.get("remeshes_within") or []:
            out["within.n"] += 1
            for k, v in (rm.get("seconds") or {}).items():
                out[f"within.{k}"] = out.get(f"within.{k}", 0.0) + v
        for k, v in (r.get("parts") or {}).items():
            out[f"stage.{k}"] = out.get(f"stage.{k}", 0.0) + v
    return out


def remesh_alone(traj, device) -> dict:
    """``S`` before and after remeshing stage 0 once more with the trajectory's remesher settings."""
    import warp as wp

    from vnc_warp.flow import _as_saved, total_complexity
    from vnc_warp.remesh import _Remesher

    p = traj.info["params"]
    m0 = _as_saved(traj.meshes[0])
    taus = np.asarray(traj.info["taus"])
    remesher = _Remesher(faces=p["faces"], resolution=p["resolution"], device=device, warn=False)
    remesher.adopt(m0, traj.info["remesh_spacing"], traj.info["source"])
    t0 = time.perf_counter()
    m1, report = remesher(positions=wp.array(m0.local_vertices, dtype=wp.vec3, device=device))
    seconds = time.perf_counter() - t0
    S0, S1 = traj.info["S_init"], total_complexity(m1, taus, kappa=p["kappa"], device=device)
    return {"dS": S1 / S0 - 1.0, "method": report.method, "why": report.why_level_set, "seconds": seconds,
            "parts": report.seconds}


def warm_up(device) -> float:
    """Seconds of a short flow of a small sphere (both remesh paths: the first one changes its face count).

    Warp compiles, or loads from its cache, each kernel module at its first launch, and the first call on a device
    creates its context: on a fresh GPU machine that charged 13.7 s to human_man's first remesh (remesh.input 2.7 s,
    remesh.checks 5.6 s; a5f9293's run, on a machine that had compiled them, took 0.7 s there). Paid here, before
    anything is timed, and reported apart.
    """
    from vnc_warp.flow import flow
    from vnc_warp.shapes import icosphere

    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        flow(icosphere(3), stages=2, faces=600, device=device, progress=False)
    return time.perf_counter() - t0


def _overrides(pairs: list[str]) -> dict:
    """``--set FIELD=VALUE`` as FlowParams keyword arguments, each VALUE read as its field's type."""
    import dataclasses

    from vnc_warp.flow import FlowParams

    fields = {f.name: f for f in dataclasses.fields(FlowParams)}
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or key not in fields:
            raise SystemExit(f"bench.flow_report: --set {pair}: expected FIELD=VALUE with FIELD one of "
                             f"{', '.join(sorted(fields))}")
        kind = type(fields[key].default)
        out[key] = (value.lower() in ("1", "true", "yes")) if kind is bool else kind(value)
    return out


def _run(path, variant, params, args):
    from vnc_warp.flow import flow
    from vnc_warp.mesh import load_mesh

    faces = args.faces
    if faces is None and args.max_faces:
        faces = min(load_mesh(path).num_faces, args.max_faces)
    name = os.path.basename(path)
    film = variant == "vnc_adaptive" and name in args.filmstrips
    out_dir = os.path.join(args.out, "trajectories", name) if film else None
    if out_dir is not None and os.path.exists(out_dir):
        import shutil

        shutil.rmtree(out_dir)  # a bench run times the whole flow: never resume an older one
    t0 = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        traj = flow(path, stages=args.stages, faces=faces, device=args.device, progress=False,
                    max_iters=args.max_iters, out_dir=out_dir, **(params | _overrides(args.set)))
    seconds = time.perf_counter() - t0
    keep = ("index", "t", "target_t", "iterations", "evaluations", "seconds", "sphericity", "thickness",
            "thickness_ratio", "thinnest", "thinnest_ratio", "euler", "status", "exception", "vertices", "faces")
    S_init = traj.info["S_init"]
    stages = [{k: r.get(k) for k in keep} | {"remesh": (r.get("remesh") or {}).get("method")} | _moves(r, S_init)
              for r in traj.records]
    run = {"mesh": name, "variant": variant, "held_out": name not in TUNED, "faces": traj.meshes[0].num_faces,
           "seconds": seconds, "stages": stages, "final_t": float(traj.t[-1]),
           "input_sphericity": traj.records[0]["sphericity"], "final_sphericity": traj.records[-1]["sphericity"],
           "warnings": [str(w.message) for w in caught], "parts": parts(traj),
           "first_remesh": {k: (traj.records[0].get("remesh") or {}).get(k)
                            for k in ("method", "spacing", "dropped_area", "lost_area", "grid_refined")}}
    if variant == "vnc_adaptive":
        run.update(summarize(traj, args.stages))
        if traj.info["params"]["remesh"]:
            run["remesh_alone"] = remesh_alone(traj, args.device)
    if film:
        from bench.flow_filmstrip import main as filmstrip

        png = os.path.join(args.out, f"filmstrip_{os.path.splitext(name)[0]}.png")
        filmstrip([out_dir, "--labels", f"{name}, {run['faces']:,} faces", "--every", str(max(args.stages // 8, 1)),
                   "--title", f"VNC-Flow, {args.stages} stages", "--device", args.device, "--out", png])
        run["filmstrip"] = png
    return run


def _faces(path: str, args) -> int:
    """The face count a run of ``path`` flows at (``--faces``, else the input's capped at ``--max-faces``)."""
    if args.faces:
        return args.faces
    import trimesh

    n = len(trimesh.load(path, process=False, force="mesh").faces)
    return min(n, args.max_faces) if args.max_faces else n


def _fmt(x, spec=".3f"):
    return "" if x is None else format(x, spec)


def summary_table(runs: list, title: str) -> list[str]:
    lines = [f"#### {title}", "",
             "| mesh | faces | max \\|t_i - (1 - i/N)\\| (exceptions out) | all stages | exceptions | smallest "
             "thickness ratio | smallest thinnest-part ratio | S change, one remesh | seconds | remesh s | stage s | "
             "final t | stages holding the previous state |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs:
        if "error" in r:
            lines.append(f"| {r['mesh']} | | error: {r['error']} | | | | | | | | | | |")
            continue
        p = r["parts"]
        rem = sum(v for k, v in p.items() if k.startswith("remesh."))
        stg = sum(v for k, v in p.items() if k.startswith("stage."))
        exc = ", ".join(f"{i}: {e}" for i, e in r["exceptions"].items())
        ra = r.get("remesh_alone") or {}
        lines.append(f"| {r['mesh']} | {r['faces']:,} | {_fmt(r['max_dt_ruled'])} | {_fmt(r['max_dt'])} | {exc} | "
                     f"{_fmt(r['min_thickness_ratio'])} | {_fmt(r.get('min_thinnest_ratio'))} | "
                     f"{_fmt(100 * ra['dS'], '+.2f') + ' %' if ra else ''} | "
                     f"{r['seconds']:.1f} | {rem:.1f} | {stg:.1f} | {r['final_t']:.3f} | "
                     f"{', '.join(map(str, r['same_mesh_stages']))} |")
    return lines


def parts_table(runs: list) -> list[str]:
    keys = ([f"remesh.{k}" for k in REMESH_PARTS] + ["within.n"] + [f"within.{k}" for k in REMESH_PARTS]
            + [f"stage.{k}" for k in STAGE_PARTS])
    lines = ["| mesh | " + " | ".join(keys) + " |", "|---|" + "---|" * len(keys)]
    for r in runs:
        if "error" not in r:
            p = r["parts"]
            lines.append(f"| {r['mesh']} | " + " | ".join(str(p.get(k, 0)) if k == "within.n" else f"{p.get(k, 0.0):.2f}"
                                                          for k in keys) + " |")
    return lines


def stage_table(run: dict, n: int) -> str:
    lines = [f"### {run['mesh']} — {run['variant']} ({run['seconds']:.1f} s, sphericity "
             f"{run['input_sphericity']:.3f} -> {run['final_sphericity']:.3f})", "",
             "| stage | t | ideal 1-i/N | t after remesh | remeshes within | iterations | evaluations | seconds | "
             "sphericity | thickness | ratio | thinnest part | ratio | Euler | remesh | status |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    refined = (run.get("first_remesh") or {}).get("grid_refined")
    if refined:  # the first remesh's grid was refined for parts thinner than the automatic one
        lines[2:2] = [f"First remesh: {refined}.", ""]
    for r in run["stages"]:
        within = ", ".join(f"{m} {a}->{b}" for m, a, b in r.get("within") or [])
        lines.append(f"| {r['index']} | {r['t']:.3f} | {1 - r['index'] / n:.3f} | {_fmt(r.get('t_start'))} | {within} | "
                     f"{r['iterations']} | "
                     f"{r.get('evaluations') or ''} | {r['seconds']:.2f} | {r['sphericity']:.3f} | "
                     f"{_fmt(r.get('thickness'))} | {_fmt(r.get('thickness_ratio'))} | {_fmt(r.get('thinnest'))} | "
                     f"{_fmt(r.get('thinnest_ratio'))} | {r.get('euler', '')} | "
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
    p.add_argument("--set", nargs="*", default=[], metavar="FIELD=VALUE",
                   help="FlowParams fields for every run (an ablation), e.g. --set step_growth=1.0 bridge=False")
    p.add_argument("--device", default=None)
    p.add_argument("--max-minutes", type=float, default=7.0,
                   help="skip a mesh when the runs so far say it would end after this many minutes")
    p.add_argument("--filmstrips", nargs="*", default=list(BODIES),
                   help="meshes whose trajectories are kept under OUT/trajectories, with a filmstrip PNG each")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)

    import warp as wp

    import vnc_warp
    from vnc_warp._device import get_device

    dev = get_device(args.device)
    args.device = str(dev)
    os.makedirs(args.out, exist_ok=True)
    names = closed_meshes(args.meshes) if args.all else list(args.names)
    first = [n for n in BODIES if n in names]
    names = first + [n for n in names if n not in first]
    jobs = [(n, "vnc_adaptive") for n in (names if not args.compare else [])]
    jobs += [(n, v) for n in args.compare for v in VARIANTS]
    report = {"device": dev.name if hasattr(dev, "name") else str(dev), "device_alias": str(dev),
              "warp": wp.__version__, "vnc_warp": vnc_warp.__version__, "python": platform.python_version(),
              "stages": args.stages, "faces": args.faces, "max_faces": args.max_faces, "tuned": list(TUNED),
              "command": "python -m bench.flow_report " + " ".join(argv if argv is not None else os.sys.argv[1:]),
              "runs": [], "skipped": []}
    report["warmup_seconds"] = warm_up(args.device)
    print(f"warm-up (kernel modules, device context): {report['warmup_seconds']:.1f} s", flush=True)
    start = time.perf_counter()
    per_face = 0.0  # the slowest finished run's seconds per face: what the next one is expected to take
    for name, variant in jobs:
        path = os.path.join(args.meshes, name)
        expected = per_face * _faces(path, args)
        if report["runs"] and time.perf_counter() - start + expected > 60 * args.max_minutes:
            report["skipped"].append({"mesh": name, "variant": variant,
                                      "why": f"time budget ({args.max_minutes:g} min; expected {expected:.0f} s)"})
            print(f"{name:24s} {variant:14s} skipped: over the {args.max_minutes:g}-minute budget", flush=True)
            continue
        try:
            run = _run(path, variant, VARIANTS[variant], args)
        except Exception as exc:  # a failing run is reported, the others still run
            report["runs"].append({"mesh": name, "variant": variant, "error": f"{type(exc).__name__}: {exc}"})
            print(f"{name:24s} {variant:14s} error: {type(exc).__name__}: {exc}", flush=True)
            continue
        report["runs"].append(run)
        per_face = max(per_face, run["seconds"] / max(run["faces"], 1))
        extra = ""
        if variant == "vnc_adaptive":
            extra = (f"  max|dt| {run['max_dt_ruled']:.3f} (all {run['max_dt']:.3f})  thickness ratio "
                     f"{_fmt(run['min_thickness_ratio'])}  thinnest-part ratio {_fmt(run['min_thinnest_ratio'])}  "
                     f"remesh alone "
                     f"{100 * run['remesh_alone']['dS']:+.2f} %" if "remesh_alone" in run else "")
        print(f"{name:24s} {variant:14s} {run['seconds']:7.1f} s  t_final {run['final_t']:.3f}{extra}", flush=True)
        with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
            json.dump(report, fh, indent=1)
    flows = [r for r in report["runs"] if r["variant"] == "vnc_adaptive"]
    body = [f"Device: {report['device']}; stages {args.stages}; faces: each input's, at most {args.max_faces:,}; "
            f"warp {report['warp']}; command: `{report['command']}`; warm-up before timing (kernel modules, device "
            f"context): {report['warmup_seconds']:.1f} s", ""]
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
    if report["skipped"]:
        body += ["Skipped (time budget): " + ", ".join(r["mesh"] for r in report["skipped"]), ""]
    with open(os.path.join(args.out, "flow_report.md"), "w") as fh:
        fh.write("\n".join(body))
    with open(os.path.join(args.out, "flow_report.json"), "w") as fh:
        json.dump(report, fh, indent=1)
    print("\n".join(body[:2 + 2 * (len(flows) + 8)]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
