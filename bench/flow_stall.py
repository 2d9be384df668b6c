"""Why a VNC-Flow stage stops descending: what each candidate move does to ``t`` at the state it stalled in.

    python -m bench.flow_stall --names hammer.obj mushroom.obj --stages 32 --device cuda --out OUT
    python -m bench.flow_stall --trajectory RUN_DIR --stage 17 --device cpu --out OUT

A stage of VNC-Flow is ``held`` (issue 21: "no descent") when neither Eq. (5) nor the smoothing fallback takes the
total VNC-AUC ``S`` below the previous stage's. For every mesh (``--names``: flowed here, its trajectory kept under
``OUT/trajectories``; or one ``--trajectory`` folder) this takes the state the first held stage started from (the
last stage that moved; ``--stage`` to pick another) and measures, each from that state, in ``t = S / S_init``
(Eq. 7, the trajectory's own scales):

* **remesh**: ``t`` after one, two and three SDF remeshes with the trajectory's remesher (the state every later
  stage starts from: Algorithm 1, line 7);
* **Eq. (5)**: the lowest ``t`` and the last ``t`` over ``--steps`` plain steps (no backtracking), evaluated every 4
  steps, from the remeshed state for the flow's parameters and for variants of the scale rule (Eq. 6's ``phi``,
  every vertex at ``tau_max``) and of the thin-part rule (``tube_rho``/``ball_rho``; 0/0 is Eq. (5) as written),
  and from the state itself (no remesh);
* **smoothing**: backward-Euler mean-curvature steps (the fallback of :mod:`vnc_warp.flow`) at each ``--dts``
  (squared mean edge lengths, the fallback's unit), ``t`` after 1, 2 and 3 steps, and the same with a volume-
  preserving term (the classical counterpart of Eq. 5: speed ``H - mean H``), from the state and from its remesh.

Prints one table per mesh and writes ``OUT/flow_stall.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings

import numpy as np

VARIANTS = (("flow's parameters", {}), ("phi_fraction 1.0", {"phi_fraction": 1.0}),
            ("phi_fraction 2.0", {"phi_fraction": 2.0}), ("every vertex at tau_max", {"scale_mode": "large"}),
            ("tube_rho 1.6, ball_rho 2.4", {"tube_rho": 1.6, "ball_rho": 2.4}),
            ("tube_rho 2.0, ball_rho 3.0", {"tube_rho": 2.0, "ball_rho": 3.0}),
            ("Eq. (5) as written (no thin-part rule)", {"tube_rho": 0.0, "ball_rho": 0.0}))


def _eq5(state, taus, params: dict, S0: float, steps: int, device) -> dict:
    from vnc_warp.flow import FlowParams, _Stepper

    st = _Stepper(state, taus, FlowParams(**params), device)
    ts = [st.S_start / S0]
    for j in range(steps):
        st.step()
        if j % 4 == 3:
            ts.append(st.complexity() / S0)
    return {"t_start": ts[0], "t_min": min(ts), "step_of_min": 4 * int(np.argmin(ts)), "t_end": ts[-1]}


def _smooth(state, taus, dt: float, S0: float, device, *, preserve_volume: bool) -> list[float]:
    """``t`` after 1, 2, 3 backward-Euler steps ``(M - dt L) x' = M x (+ dt 2 mean(H) A n)``, dt in squared mean edge
    lengths; the volume-preserving term moves every vertex out by the mean of the cotangent mean curvature, and the
    step is scaled back to the volume it started from."""
    import warp as wp

    from vnc_warp._reduce import face_measures, vertex_normals
    from vnc_warp.flow import FlowParams, _Stepper

    st = _Stepper(state, taus, FlowParams(method="mcf_implicit", mcf_dt=dt), device)
    area = st.M.diagonal()
    out = []
    for _ in range(3):
        v = st.x.numpy().astype(np.float64)
        rhs = st.M @ v
        if preserve_volume:
            n = vertex_normals(st.x, st.surface.tri).numpy().astype(np.float64)
            two_h = -np.sum((st.L @ v) * n) / area.sum()
            rhs = rhs + st.dt * two_h * area[:, None] * n
        volume = face_measures(st.x, st.surface.tri)[1]
        v = np.stack([st.solve(rhs[:, d]) for d in range(3)], axis=1)
        st.x = wp.array(v.astype(np.float32), dtype=wp.vec3, device=st.device)
        if preserve_volume:  # as the fallback of vnc_warp.flow: scaled back to the volume before the step
            c = v.mean(axis=0)
            v = c + (v - c) * (volume / face_measures(st.x, st.surface.tri)[1]) ** (1.0 / 3.0)
            st.x = wp.array(v.astype(np.float32), dtype=wp.vec3, device=st.device)
        out.append(st.complexity() / S0)
    return out


def diagnose(run_dir: str, stage: int | None, *, dts, steps: int, device) -> dict:
    """The measurements of the module docstring at stage ``stage`` of the trajectory in ``run_dir`` (None: the state
    the first ``held`` stage started from)."""
    import warp as wp

    from vnc_warp.flow import _as_saved, sphericity, total_complexity
    from vnc_warp.mesh import load_mesh
    from vnc_warp.remesh import _Remesher

    with open(os.path.join(run_dir, "manifest.json")) as fh:
        man = json.load(fh)
    recs = man["stages"]
    held = [r["index"] for r in recs if r["status"] == "held"]
    if stage is None:
        if not held:
            return {"run": run_dir, "held": [], "note": "no held stage"}
        stage = held[0] - 1
    taus, S0, p = np.asarray(man["taus"]), man["S_init"], man["params"]
    flow_params = {k: p[k] for k in ("stages", "kappa", "step_fraction", "max_lambda", "phi_fraction", "tube_rho",
                                     "ball_rho")}
    state = _as_saved(load_mesh(os.path.join(run_dir, f"stage_{stage:03d}.ply")))
    rem = _Remesher(faces=p["faces"], resolution=p["resolution"], device=device, warn=False)
    rem.adopt(state, man["remesh_spacing"], "stall")
    remeshes, cur = [], state
    for _ in range(3):
        cur, report = rem(positions=wp.array(cur.local_vertices, dtype=wp.vec3, device=device))
        cur = _as_saved(cur)
        remeshes.append({"t": total_complexity(cur, taus, kappa=p["kappa"], device=device) / S0,
                         "method": report.method, "euler": report.euler})
        if len(remeshes) == 1:
            remeshed = cur
    doc = {"run": run_dir, "held": held, "stage": stage, "t_recorded": recs[stage]["t"],
           "t_state": total_complexity(state, taus, kappa=p["kappa"], device=device) / S0,
           "sphericity": sphericity(state), "faces": state.num_faces, "remesh": remeshes,
           "eq5_remeshed": [{"variant": name, **_eq5(remeshed, taus, flow_params | kw, S0, steps, device)}
                            for name, kw in VARIANTS],
           "eq5_state": _eq5(state, taus, flow_params, S0, steps, device), "smoothing": []}
    for base, mesh in (("state", state), ("remeshed", remeshed)):
        for vp in (False, True):
            for dt in dts:
                doc["smoothing"].append({"from": base, "volume_preserving": vp, "dt": dt,
                                         "t": _smooth(mesh, taus, dt, S0, device, preserve_volume=vp)})
    return doc


def table(doc: dict) -> list[str]:
    if "stage" not in doc:
        return [f"{doc['run']}: {doc['note']}"]
    f = lambda x: f"{x:.4f}"  # noqa: E731
    lines = [f"### {doc['run']}: stage {doc['stage']} ({doc['faces']:,} faces, sphericity {doc['sphericity']:.3f}); "
             f"held stages {doc['held']}", "",
             f"t recorded {f(doc['t_recorded'])}, recomputed {f(doc['t_state'])}; after 1, 2, 3 remeshes: "
             + ", ".join(f(r["t"]) for r in doc["remesh"]), "",
             "| Eq. (5) from | variant | t start | lowest t (step) | t at the end |", "|---|---|---|---|---|"]
    for r in doc["eq5_remeshed"]:
        lines.append(f"| remesh | {r['variant']} | {f(r['t_start'])} | {f(r['t_min'])} ({r['step_of_min']}) | "
                     f"{f(r['t_end'])} |")
    r = doc["eq5_state"]
    lines += [f"| state | flow's parameters | {f(r['t_start'])} | {f(r['t_min'])} ({r['step_of_min']}) | "
              f"{f(r['t_end'])} |", "", "| smoothing from | volume-preserving | dt (edge^2) | t after 1, 2, 3 steps |",
              "|---|---|---|---|"]
    for r in doc["smoothing"]:
        lines.append(f"| {r['from']} | {'yes' if r['volume_preserving'] else 'no'} | {r['dt']:g} | "
                     + ", ".join(f(x) for x in r["t"]) + " |")
    return lines


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--meshes", default=os.path.join(os.path.dirname(__file__), "..", "..", "shared", "data", "meshes"))
    ap.add_argument("--names", nargs="*", default=[], help="meshes to flow and diagnose")
    ap.add_argument("--trajectory", help="a VNC-Flow output folder to diagnose instead")
    ap.add_argument("--stage", type=int, default=None, help="the stage to diagnose (default: before the first held)")
    ap.add_argument("--stages", type=int, default=32)
    ap.add_argument("--faces", type=int, default=None, help="face count (default: each input's, capped)")
    ap.add_argument("--max-faces", type=int, default=50000)
    ap.add_argument("--steps", type=int, default=48, help="Eq. (5) steps per variant")
    ap.add_argument("--dts", type=float, nargs="*", default=[1.0, 4.0, 16.0, 64.0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    if not args.names and not args.trajectory:
        ap.error("give --names or --trajectory")
    os.makedirs(args.out, exist_ok=True)
    docs = []
    runs = [args.trajectory] if args.trajectory else []
    for name in args.names:
        import trimesh

        from vnc_warp.flow import flow

        path = os.path.join(args.meshes, name)
        faces = args.faces or min(len(trimesh.load(path, process=False, force="mesh").faces), args.max_faces)
        run_dir = os.path.join(args.out, "trajectories", name)
        t0 = time.perf_counter()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            flow(path, stages=args.stages, faces=faces, device=args.device, progress=False, out_dir=run_dir)
        print(f"{name}: flowed {args.stages} stages at {faces:,} faces in {time.perf_counter() - t0:.1f} s", flush=True)
        runs.append(run_dir)
    for run_dir in runs:
        doc = diagnose(run_dir, args.stage, dts=args.dts, steps=args.steps, device=args.device)
        docs.append(doc)
        print("\n".join(table(doc)) + "\n", flush=True)
    result = {"command": "python -m bench.flow_stall " + " ".join(sys.argv[1:] if argv is None else argv),
              "device": args.device, "platform": platform.platform(), "runs": docs}
    with open(os.path.join(args.out, "flow_stall.json"), "w") as fh:
        json.dump(result, fh, indent=1)
    return result


if __name__ == "__main__":
    main()
