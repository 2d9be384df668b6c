"""Host time per call of the VNC operator on a tiny mesh, where kernel time is negligible: the fixed Python cost of
the calls that ``python -m bench.vnc`` times on a GPU (own vertices, ``positions=``, the torch op forward and forward
+ backward), and the own-vertices calls of VNC-soft and VNC-hard with ``strategy="auto"`` beside the strategy it
chooses named explicitly (the same launches: any gap is host time spent choosing).

Runs on the CPU device with graph replay on (``Tuning(replay=("cpu", "cuda"))``), so that repeated calls take the
replayed path a CUDA call takes. On the CPU a replayed graph runs its kernels inside ``wp.capture_launch``: the time
spent there is measured apart and left out of the "host" column (on CUDA that call only enqueues the graph). Prints a
table (median microseconds per call over ``--repeats`` runs of ``--calls`` calls) and, with ``--out``, writes it as
JSON; the rows take turns (one run of ``--calls`` calls each, ``--repeats`` rounds, each round in another order),
so that a slow spell of a shared machine, a GPU's clocks or what the row before left behind fall on every row alike
(on nefertiti, with the rows always in one order, the row after the torch op's took 146-157 us of host time per
call against 97-102 us for the same calls elsewhere). ``--mesh PATH`` and ``--tau`` (mean edge lengths) time a
mesh of one's own instead of the icosphere. ``--profile NAME`` prints a cProfile of one row instead. ``--host-only`` replaces ``wp.capture_launch`` by a
no-op after the warm-up (the results are then meaningless; the Python path is the same): the steadiest measure of the
host cost on a loaded machine; ``--cpu-time`` times with the process's CPU time instead of the wall clock (time spent
waiting for a core on a shared machine is left out; every thread's time is counted, torch's intra-op threads too).
``--device cuda:0`` times the same calls on a GPU, where "total" is the figure.

    python -m bench.overhead                      # the table
    python -m bench.overhead --profile positions  # where that row's host time goes
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time
from pathlib import Path

import numpy as np
import torch
import warp as wp

import vnc_warp as vw
from vnc_warp.torch import vnc_soft as vnc_soft_torch
from vnc_warp.tuning import Tuning


_in_graph = [0.0]
_clock = [time.perf_counter]


def _timed_capture_launch(launch):
    def timed(*args, **kwargs):
        t0 = _clock[0]()
        try:
            return launch(*args, **kwargs)
        finally:
            _in_graph[0] += _clock[0]() - t0

    return timed


def rows(subdivisions: int, device: str, mesh_path: Path | None = None, edges: float = 4.0) -> dict:
    """name -> a function making one call, each warmed up past graph capture."""
    mesh = vw.icosphere(subdivisions) if mesh_path is None else vw.load_mesh(mesh_path)
    tuning = Tuning(replay=("cpu", "cuda"))
    eng = vw.engine(mesh, device, tuning=tuning)
    tau = edges * mesh.mean_edge_length
    soft_choice = vw.choose_strategy(mesh, tau, device=device, tuning=tuning)
    hard_choice = vw.choose_strategy(mesh, tau, variant="hard", device=device, tuning=tuning)
    x = wp.array(mesh.local_vertices, dtype=wp.vec3, device=device)
    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=device).requires_grad_(True)
    vd = v.detach()

    def own():
        vw.vnc_soft(mesh, tau, tuning=tuning, device=device)

    def own_named():
        vw.vnc_soft(mesh, tau, tuning=tuning, device=device, strategy=soft_choice)

    def hard():
        vw.vnc_hard(mesh, tau, tuning=tuning, device=device)

    def hard_named():
        vw.vnc_hard(mesh, tau, tuning=tuning, device=device, strategy=hard_choice)

    def engine_own():
        eng.vnc_soft(tau)

    def positions():
        eng.vnc_soft(tau, positions=x)

    def torch_fwd():
        with torch.no_grad():
            vnc_soft_torch(vd, mesh, tau, tuning=tuning)

    def torch_fwd_bwd():
        H, n = vnc_soft_torch(v, mesh, tau, tuning=tuning)
        (H.sum() + n[:, 2].sum()).backward()
        v.grad = None

    fns = {"vw.vnc_soft": own, f"vw.vnc_soft {soft_choice}": own_named, "vw.vnc_hard": hard,
           f"vw.vnc_hard {hard_choice}": hard_named, "engine.vnc_soft": engine_own, "positions": positions, "torch_fwd": torch_fwd,
           "torch_fwd+bwd": torch_fwd_bwd}
    for fn in fns.values():
        for _ in range(5):
            fn()
    return fns


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--subdivisions", type=int, default=2, help="icosphere subdivisions (2: 162 vertices)")
    p.add_argument("--mesh", type=Path, default=None, help="a mesh file instead of the icosphere")
    p.add_argument("--tau", type=float, default=4.0, help="the scale in mean edge lengths")
    p.add_argument("--calls", type=int, default=200)
    p.add_argument("--repeats", type=int, default=7)
    p.add_argument("--device", default="cpu")
    p.add_argument("--profile", default=None, help="a row name: print its cProfile instead of the table")
    p.add_argument("--out", type=Path, default=None, help="JSON file to write the table to")
    p.add_argument("--host-only", action="store_true", help="replayed graphs do nothing (host path only)")
    p.add_argument("--cpu-time", action="store_true", help="the process's CPU time instead of the wall clock")
    a = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    fns = rows(a.subdivisions, a.device, a.mesh, a.tau)
    if a.host_only:
        wp.capture_launch = lambda *args, **kwargs: None
    if a.profile:
        fn = fns[a.profile]
        prof = cProfile.Profile()
        prof.enable()
        for _ in range(a.calls):
            fn()
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(30)
        return
    wp.capture_launch = _timed_capture_launch(wp.capture_launch)
    clock = _clock[0] = time.process_time if a.cpu_time else time.perf_counter
    total = {name: [] for name in fns}
    host = {name: [] for name in fns}
    names = list(fns)
    rng = np.random.default_rng(0)
    for _ in range(a.repeats):
        for k in rng.permutation(len(names)):
            name = names[k]
            fn = fns[name]
            wp.synchronize_device(a.device)
            _in_graph[0] = 0.0
            t0 = clock()
            for _ in range(a.calls):
                fn()
            wp.synchronize_device(a.device)
            dt = clock() - t0
            total[name].append(dt / a.calls * 1e6)
            host[name].append((dt - _in_graph[0]) / a.calls * 1e6)
    table = {name: {"host_us": float(np.median(host[name])), "host_min_us": float(np.min(host[name])),
                    "total_us": float(np.median(total[name]))} for name in fns}
    what = f"icosphere({a.subdivisions})" if a.mesh is None else a.mesh.name
    print(f"{what}, tau {a.tau:g} mean edge lengths, device {a.device}, replay on{', graphs not run' if a.host_only else ''}"
          f"{', CPU time' if a.cpu_time else ''}; us per "
          f"call, median (min) of {a.repeats} x {a.calls} calls; host = total less the replayed graphs")
    print("| call | host us | min | total us |\n|---|---|---|---|")
    for name, r in table.items():
        print(f"| {name} | {r['host_us']:.1f} | {r['host_min_us']:.1f} | {r['total_us']:.1f} |")
    if a.out:
        a.out.write_text(json.dumps({"subdivisions": a.subdivisions, "mesh": None if a.mesh is None else str(a.mesh),
                                     "tau_edges": a.tau, "device": a.device, "host_only": a.host_only,
                                     "cpu_time": a.cpu_time, "rows": table}, indent=1))


if __name__ == "__main__":
    main()
