"""Where the time of one operator call goes: host (Python + launches) against device (each kernel).

    python -m bench.breakdown --device cuda:0 --mesh nefertiti.obj --taus 2 8 diag/2 --out breakdown.json

For each operator and scale it reports the wall time of a synchronized call (median), the host time to
enqueue it (the call without the final synchronization; a call that reads a result on the host in the middle
includes that wait), the device busy time summed over its kernels and copies, and the kernels by time (on the CPU
device: each launch's thread CPU time, which other processes on the machine do not inflate). This is
the tool for deciding whether a call is launch-bound (host time close to wall time) or kernel-bound.

``--ops torch`` times the torch op's VNC-soft forward + backward (:func:`vnc_warp.torch.vnc_soft`, as bench.vnc's
``vnc_soft_fwd+bwd`` row): with ``--no-graphs`` its kernels show how the backward's cost splits between the forward's
moments, the edge adjoint and the small kernels around them; ``--vertex-scatter cpu,cuda`` times it with the vertices'
part added by the edge adjoint instead (``Tuning.vertex_scatter``).
"""

from __future__ import annotations

import argparse
import json
import re
import time
from pathlib import Path

import numpy as np
import warp as wp

import vnc_warp as vw
from vnc_warp._device import get_device
from vnc_warp.tuning import Tuning

from .vnc import MESH_DIR


def _tau(mesh: vw.Mesh, spec: str) -> float:
    if spec.startswith("diag/"):
        return mesh.bbox_diagonal / float(spec[5:])
    return float(spec) * mesh.mean_edge_length


def load(spec: str, subdivide: int = 0) -> vw.Mesh:
    """A mesh file (in ../shared/data/meshes or a path), midpoint-subdivided ``subdivide`` times (as bench.vnc's
    200k and 800k sizes)."""
    path = Path(spec) if Path(spec).exists() else MESH_DIR / spec
    mesh = vw.load_mesh(path)
    if subdivide:
        tm = mesh.to_trimesh()
        for _ in range(subdivide):
            tm = tm.subdivide()
        mesh = vw.load_mesh(tm, name=f"{path.stem}-sub{subdivide}")
    return mesh


def _median_ms(fn, device, repeats: int, sync: bool) -> float:
    out = []
    for _ in range(repeats):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        fn()
        if sync:
            wp.synchronize_device(device)
        out.append(1e3 * (time.perf_counter() - t0))
    wp.synchronize_device(device)
    return float(np.median(out))


def _kernels(fn, device) -> tuple[float, dict]:
    per: dict[str, list] = {}
    if device.is_cuda:
        wp.timing_begin(cuda_filter=wp.TIMING_ALL)
        fn()
        for r in wp.timing_end():
            name = re.sub(r"_[0-9a-f]{8}$", "", r.name.replace("forward kernel ", ""))
            per.setdefault(name, [0.0, 0])
            per[name][0] += r.elapsed
            per[name][1] += 1
    else:
        # the CPU device runs a kernel on the launching thread before wp.launch returns: its thread CPU time is the
        # kernel's, whatever else the machine runs
        launch = wp.launch

        def timed(kernel, *args, **kwargs):
            t0 = time.thread_time()
            try:
                return launch(kernel, *args, **kwargs)
            finally:
                name = re.sub(r"_[0-9a-f]{8}$", "", kernel.key.split("__locals__")[-1])
                per.setdefault(name, [0.0, 0])
                per[name][0] += 1e3 * (time.thread_time() - t0)
                per[name][1] += 1

        wp.launch = timed
        try:
            fn()
        finally:
            wp.launch = launch
    busy = float(sum(v[0] for v in per.values()))
    top = {k: {"ms": round(v[0], 4), "count": v[1]} for k, v in sorted(per.items(), key=lambda kv: -kv[1][0])}
    return busy, top


def _torch_fwd_bwd(mesh: vw.Mesh, tau: float, device, tuning: Tuning | None):
    """One forward + backward pass of the torch op's VNC-soft on ``device`` (the loss of bench.vnc's row)."""
    import torch

    from vnc_warp.torch import vnc_soft

    v = torch.tensor(mesh.vertices, dtype=torch.float32, device=wp.device_to_torch(device), requires_grad=True)

    def fn():
        H, n = vnc_soft(v, mesh, tau, tuning=tuning)
        (H.sum() + n[:, 2].sum()).backward()
        v.grad = None

    return fn


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--mesh", default="nefertiti.obj", help="a file in ../shared/data/meshes or a path")
    ap.add_argument("--subdivide", type=int, default=0, help="midpoint-subdivide the mesh this many times")
    ap.add_argument("--taus", nargs="+", default=["2", "8", "diag/4", "diag/2"],
                    help="multiples of the mean edge length, or diag/N")
    ap.add_argument("--ops", nargs="+", default=["soft", "hard", "curve"],
                    choices=["soft", "soft_x", "torch", "hard", "curve"],
                    help="soft_x: VNC-soft with the positions given as a device array (as a flow step calls it); "
                         "torch: the torch op's VNC-soft forward + backward")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--no-graphs", action="store_true",
                    help="run every call as launched (no graph replay: Tuning(replay=())), to see its kernels")
    ap.add_argument("--vertex-scatter", default=None, metavar="KINDS",
                    help="Tuning.vertex_scatter as comma-separated device kinds ('cpu,cuda'; '' for none): where the "
                         "torch op's backward adds the vertices' part from the edge adjoint's pairs")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    device = get_device(args.device)
    tuning = Tuning(replay=()) if args.no_graphs else None
    if args.vertex_scatter is not None:
        kinds = tuple(k for k in args.vertex_scatter.split(",") if k)
        tuning = (tuning or Tuning()).replace(vertex_scatter=kinds)
    mesh = load(args.mesh, args.subdivide)
    x = wp.array(mesh.vertices, dtype=wp.vec3, device=device)
    rows = []
    print(f"{mesh.name}: V={mesh.num_vertices} on {device} ({getattr(device, 'name', device)})")
    print(f"{'op':6} {'tau':>8} {'wall ms':>9} {'host ms':>9} {'device ms':>10}  kernels (ms x count)")
    for op in args.ops:
        for spec in args.taus if op != "curve" else ["16 scales"]:
            if op == "soft":
                tau = _tau(mesh, spec)
                fn = lambda tau=tau: vw.vnc_soft(mesh, tau, device=device, tuning=tuning)  # noqa: E731
            elif op == "soft_x":
                tau = _tau(mesh, spec)
                fn = lambda tau=tau: vw.vnc_soft(mesh, tau, positions=x, tuning=tuning)  # noqa: E731
            elif op == "torch":
                fn = _torch_fwd_bwd(mesh, _tau(mesh, spec), device, tuning)
            elif op == "hard":
                tau = _tau(mesh, spec)
                fn = lambda tau=tau: vw.vnc_hard(mesh, tau, device=device, tuning=tuning)  # noqa: E731
            else:
                c = vw.scale_curve(mesh, device=device, tuning=tuning)
                phi = float(np.median(vw.vnc_auc(c).numpy()))

                def fn(phi=phi):
                    c = vw.scale_curve(mesh, device=device, tuning=tuning)
                    vw.vnc_auc(c)
                    vw.adaptive_scale(c, phi=phi)
            fn()
            wp.synchronize_device(device)
            wall = _median_ms(fn, device, args.repeats, True)
            host = _median_ms(fn, device, args.repeats, False)
            busy, top = _kernels(fn, device)
            shown = ", ".join(f"{k} {v['ms']:.3f}x{v['count']}" for k, v in list(top.items())[:6])
            print(f"{op:6} {spec:>8} {wall:9.3f} {host:9.3f} {busy:10.3f}  {shown}")
            rows.append({"op": op, "tau": spec, "wall_ms": wall, "host_ms": host, "device_ms": busy, "kernels": top})
    if args.out:
        Path(args.out).write_text(json.dumps({"mesh": mesh.name, "V": mesh.num_vertices, "device": str(device),
                                              "vertex_scatter": args.vertex_scatter, "rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
