"""What one operator call asks of the device, counted on any device (the CPU too): kernel launches, graph launches,
copies, memsets, sorts and scans, and reads back to the host (each a wait for the device on CUDA).

    python -m bench.counts --mesh spot_lowres.obj --device cpu --out counts.json

A read back (``wp.array.numpy()`` of a device array, a ``float()`` of one) stalls the host until the device has done
everything queued before it; a call that reads nothing back lets the host queue the next call while the device works.
:func:`counting` wraps Warp's entry points for the duration of a ``with`` block (and restores them): it measures the
package as any caller sees it, whatever its version, so the same command counts an older checkout too. On the CPU
device every Warp array is host memory, so the reads counted are those that would wait on CUDA: ``.numpy()`` of an
array on the computing device, by the package rather than by the caller.
"""

from __future__ import annotations

import argparse
import contextlib
import json
from collections import Counter
from pathlib import Path

import numpy as np
import warp as wp

import vnc_warp as vw
from vnc_warp._device import get_device
from vnc_warp._replay import capture_failures

from .breakdown import _tau, load

_WRAPPED = (
    ("launch", wp, "launch"),
    ("graph launch", wp, "capture_launch"),
    ("copy", wp, "copy"),
    ("sort", wp.utils, "radix_sort_pairs"),
    ("scan", wp.utils, "array_scan"),
    ("memset", wp.array, "fill_"),
    ("memset", wp.array, "zero_"),
    ("read back", wp.array, "numpy"),
)


@contextlib.contextmanager
def counting(device: wp.Device):
    """Count the Warp operations inside the block (a Counter, filled as it runs); ``read back`` counts ``.numpy()`` of
    arrays on ``device`` made by the package (those the block's own code reads are excluded by the caller)."""
    counts: Counter = Counter()
    saved = []
    for kind, owner, name in _WRAPPED:
        original = getattr(owner, name)
        saved.append((owner, name, original))

        def wrapper(*args, _original=original, _kind=kind, **kwargs):
            if _kind == "read back":
                if args[0].device != device:
                    return _original(*args, **kwargs)
            elif _kind == "launch" and kwargs.get("adjoint"):
                counts["launch (adjoint)"] += 1
                return _original(*args, **kwargs)
            counts[_kind] += 1
            return _original(*args, **kwargs)

        setattr(owner, name, wrapper)
    try:
        yield counts
    finally:
        for owner, name, original in reversed(saved):
            setattr(owner, name, original)


def calls(mesh: vw.Mesh, device: wp.Device, spec: str) -> dict:
    """The calls counted, each a function of no argument (warmed up first): VNC-soft on the mesh's own vertices, with
    ``positions=`` (a flow step: a new position array every call), and through the torch op, forward and backward."""
    import torch

    tau = _tau(mesh, spec)
    base = np.asarray(mesh.vertices, np.float32)
    steps = [wp.array(base * np.float32(1.0 + 1e-4 * k), dtype=wp.vec3, device=device) for k in range(4)]
    step = iter(range(10**9))
    tdev = torch.device("cuda" if device.is_cuda else "cpu")
    v = torch.tensor(base, device=tdev, requires_grad=True)

    def torch_op():
        from vnc_warp.torch import vnc_soft

        H, n = vnc_soft(v, mesh, tau)
        (H.sum() + n[:, 2].sum()).backward()
        v.grad = None

    return {
        "vnc_soft (own vertices)": lambda: vw.vnc_soft(mesh, tau, device=device),
        "vnc_soft (positions=)": lambda: vw.vnc_soft(mesh, tau, positions=steps[next(step) % len(steps)]),
        "torch vnc_soft forward + backward": torch_op,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--mesh", default="spot_lowres.obj", help="a file in ../shared/data/meshes, a path, or a "
                                                             "name vnc_warp.data bundles")
    ap.add_argument("--tau", default="4", help="the scale: mean edge lengths, or diag/N")
    ap.add_argument("--replay", choices=["device", "on", "off"], default="on",
                    help="graph replay as the device's default (off on the CPU), on (as on CUDA), or off")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    device = get_device(args.device)
    try:
        mesh = load(args.mesh)
    except Exception:
        from vnc_warp.data import mesh_path

        mesh = vw.load_mesh(mesh_path(Path(args.mesh).stem.replace("_lowres", "")))
    old = None if args.replay == "device" else vw.set_graph_replay(*(("cpu", "cuda") if args.replay == "on" else ()))
    rows = {}
    try:
        with wp.ScopedDevice(device):
            for name, fn in calls(mesh, device, args.tau).items():
                for _ in range(4):  # the plan, the graph's scratch, the capture: then every call replays
                    fn()
                with counting(device) as c:
                    fn()
                rows[name] = dict(sorted(c.items()))
    finally:
        if old is not None:
            vw.set_graph_replay(*old)
    print(f"{mesh.name}: V={mesh.num_vertices} on {device}, tau {args.tau}, graph replay {args.replay} "
          f"(vnc_warp from {Path(vw.__file__).parent})")
    for name, c in rows.items():
        print(f"  {name:36s} " + ", ".join(f"{k} {v}" for k, v in c.items()))
    failures = capture_failures()
    for kind, error in failures:
        print(f"  graph capture failed ({kind}): {error}")
    if args.out:
        Path(args.out).write_text(json.dumps({"mesh": mesh.name, "V": mesh.num_vertices, "device": str(device),
                                              "tau": args.tau, "replay": args.replay,
                                              "vnc_warp": str(Path(vw.__file__).parent), "calls": rows,
                                              "capture_failures": failures}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
