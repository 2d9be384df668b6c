"""How the traversal's knobs were chosen: VNC-soft and VNC-hard timed over a grid of settings, per scale.

    python -m bench.tune --device cuda:0 --mesh nefertiti.obj --out tune.json

The knobs (module attributes, set for the run and restored after):

* ``qb``: queries per thread of the forward kernels in a busy traversal (``vnc_warp.kernels.vnc.QB``);
* ``busy``: candidates per query from which a traversal counts as busy (``vnc_warp._pairs.BUSY_SOURCES``: several
  queries per thread and more splits; 0: every traversal, inf: none);
* ``splits``: how many ways a box's rows are shared (``None``: :func:`vnc_warp._pairs.launch_shape`'s choice);
* ``cell``: grid cell size as a fraction of the typical radius (``vnc_warp._pairs.CELL_FRACTION``);
* ``spread``: the per-thread box threshold (``vnc_warp._pairs.SPREAD``);
* ``fine``: VNC-hard's Morton bits ordering the edges within a cell (``vnc_warp._pairs.FINE_BITS``);
* ``bcell``: VNC-hard's cell size in a busy traversal (``vnc_warp._pairs.BUSY_BALL_CELL``);
* ``tier``: VNC-hard's first edge-length tier in mean edge lengths (``vnc_warp._pairs.TIER_BASE``): with pieces of
  the edges (``vnc_warp._pairs.PIECES``), the longest edge that needs none;
* ``kernel``: VNC-hard's kernel variant (``BALL_KERNELS`` below, set as ``vnc_warp.kernels.vnc.BALL_VARIANT``): a
  variant of "half" records takes edge-length tiers, since only "unit" records hold pieces of edges.

Every setting gives the same sums (the tests check all of them against the BVH); only the time differs. The
table prints the median wall time of a synchronized call per setting and scale, and the best setting per scale.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np
import warp as wp

import vnc_warp as vw
from vnc_warp import _pairs, _replay
from vnc_warp._device import get_device
from vnc_warp.kernels import vnc as _k

from .breakdown import _tau, load
from .vnc import measure


# kernel variants of VNC-hard (``vnc_warp.kernels.vnc.ball_cells_kernel``): the edge records ("unit": midpoint and unit
# direction, "half": midpoint and half-vector), runs of records tested as a whole first ("chunks"), the midpoint
# prefilter; None: chosen per traversal (``ball_variant``), as in "auto", the default
BALL_KERNELS = {
    "auto": {"prefilter": None, "form": None, "chunks": None},
    "unit": {"prefilter": None, "form": "unit", "chunks": False},
    "half": {"prefilter": None, "form": "half", "chunks": False},
    "unit_chunks": {"prefilter": None, "form": "unit", "chunks": True},
    "half_chunks": {"prefilter": None, "form": "half", "chunks": True},
    "plain": {"prefilter": False, "form": None, "chunks": None},
    "prefilter": {"prefilter": True, "form": None, "chunks": None},
    "half_prefilter": {"prefilter": True, "form": "half", "chunks": None},
    "unit_plain": {"prefilter": False, "form": "unit", "chunks": None},
}


def _variant_name(table: dict, variant: dict) -> str:
    return next((k for k, v in table.items() if v == variant), str(variant))


def apply(setting: dict) -> dict:
    """Set the knobs of ``setting``; returns the previous values (``apply(old)`` restores them)."""
    old = {"qb": _k.QB, "splits": _pairs.SPLITS, "cell": _pairs.CELL_FRACTION, "spread": _pairs.SPREAD,
           "busy": _pairs.BUSY_SOURCES, "tier": _pairs.TIER_BASE, "fine": _pairs.FINE_BITS,
           "bcell": _pairs.BUSY_BALL_CELL, "ball_kernel": _variant_name(BALL_KERNELS, _k.BALL_VARIANT)}
    if "ball_kernel" in setting:
        _k.BALL_VARIANT = dict(BALL_KERNELS[setting["ball_kernel"]])
    _k.QB = int(setting.get("qb", old["qb"]))
    _pairs.SPLITS = setting.get("splits", old["splits"])
    _pairs.CELL_FRACTION = float(setting.get("cell", old["cell"]))
    _pairs.SPREAD = float(setting.get("spread", old["spread"]))
    _pairs.BUSY_SOURCES = float(setting.get("busy", old["busy"]))
    _pairs.TIER_BASE = float(setting.get("tier", old["tier"]))
    _pairs.FINE_BITS = int(setting.get("fine", old["fine"]))
    _pairs.BUSY_BALL_CELL = float(setting.get("bcell", old["bcell"]))
    _pairs.Pool.clear()
    return old


def settings(grid: dict) -> list[dict]:
    keys = list(grid)
    return [dict(zip(keys, values)) for values in itertools.product(*(grid[k] for k in keys))]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None)
    ap.add_argument("--mesh", default="nefertiti.obj", help="a file in ../shared/data/meshes or a path")
    ap.add_argument("--subdivide", type=int, default=0, help="midpoint-subdivide the mesh this many times")
    ap.add_argument("--taus", nargs="+", default=["2", "4", "8", "16", "32", "diag/8", "diag/4", "diag/2"])
    ap.add_argument("--ops", nargs="+", default=["soft", "hard"], choices=["soft", "hard"])
    ap.add_argument("--qb", nargs="+", type=int, default=[4, 8])
    ap.add_argument("--splits", nargs="+", default=["auto", "4", "8", "16"])
    ap.add_argument("--cell", nargs="+", type=float, default=[0.5, 1.0])
    ap.add_argument("--spread", nargs="+", type=float, default=[8.0, 2.0])
    ap.add_argument("--busy", nargs="+", type=float, default=[2000.0])
    ap.add_argument("--tier", nargs="+", type=float, default=[_pairs.TIER_BASE],
                    help="VNC-hard's first edge-length tier, in mean edge lengths (vnc_warp._pairs.TIER_BASE)")
    ap.add_argument("--fine", nargs="+", type=int, default=[_pairs.FINE_BITS],
                    help="VNC-hard's Morton bits within a cell (vnc_warp._pairs.FINE_BITS)")
    ap.add_argument("--busy-cell", nargs="+", type=float, default=[_pairs.BUSY_BALL_CELL],
                    help="VNC-hard's cell size in a busy traversal, as a fraction of the reach (_pairs.BUSY_BALL_CELL)")
    ap.add_argument("--ball-kernels", nargs="+", default=["auto"], choices=list(BALL_KERNELS))
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    device = get_device(args.device)
    mesh = load(args.mesh, args.subdivide)
    base = {"qb": args.qb, "splits": [None if s == "auto" else int(s) for s in args.splits], "cell": args.cell,
            "spread": args.spread, "busy": args.busy}
    grids = {"soft": {**base, "tier": [_pairs.TIER_BASE], "fine": [_pairs.FINE_BITS],
                     "bcell": [_pairs.BUSY_BALL_CELL], "kernel": ["default"]},
             "hard": {**base, "tier": args.tier, "fine": args.fine, "bcell": args.busy_cell,
                     "kernel": args.ball_kernels}}
    rows = []
    print(f"{mesh.name}: V={mesh.num_vertices} on {device}")
    print(f"{'op':5} {'tau':>7} {'qb':>3} {'splits':>6} {'cell':>5} {'spread':>6} {'busy':>6} {'tier':>4} {'fine':>4} {'bcell':>5} "
          f"{'kernel':>11} {'ms':>8}")
    for op in args.ops:
        fn_op = vw.vnc_soft if op == "soft" else vw.vnc_hard
        for spec in args.taus:
            tau = _tau(mesh, spec)
            for st in settings(grids[op]):
                old = apply({**st, **({"ball_kernel": st["kernel"]} if op == "hard" else {})})
                _replay.forget(mesh)  # graphs captured under other settings
                try:
                    t = measure(lambda: fn_op(mesh, tau, device=device), device, target_s=0.05,
                                max_repeats=args.repeats, min_repeats=3)["median_ms"]
                finally:
                    apply(old)
                    _replay.forget(mesh)
                rows.append({"op": op, "tau": spec, **st, "ms": t})
                print(f"{op:5} {spec:>7} {st['qb']:>3} {str(st['splits']):>6} {st['cell']:>5} {st['spread']:>6} "
                      f"{st['busy']:>6g} {st['tier']:>4g} {st['fine']:>4} {st['bcell']:>5} {st['kernel']:>11} {t:8.3f}", flush=True)
    print("\nbest per scale (default setting's time in brackets):")
    default = {"qb": _k.QB, "splits": _pairs.SPLITS, "cell": _pairs.CELL_FRACTION, "spread": _pairs.SPREAD,
               "busy": _pairs.BUSY_SOURCES, "tier": _pairs.TIER_BASE, "fine": _pairs.FINE_BITS,
               "bcell": _pairs.BUSY_BALL_CELL}
    for op in args.ops:
        default["kernel"] = "default" if op == "soft" else _variant_name(BALL_KERNELS, _k.BALL_VARIANT)
        for spec in args.taus:
            rs = [r for r in rows if r["op"] == op and r["tau"] == spec]
            best = min(rs, key=lambda r: r["ms"])
            d = [r["ms"] for r in rs if all(r[k] == v for k, v in default.items())]
            print(f"{op:5} {spec:>7}: {best['ms']:.3f} ms at qb={best['qb']} splits={best['splits']} "
                  f"cell={best['cell']} spread={best['spread']} busy={best['busy']:g} tier={best['tier']:g} "
                  f"fine={best['fine']} bcell={best['bcell']} "
                  f"kernel={best['kernel']}  "
                  f"[{d[0] if d else float('nan'):.3f}]")
    # per op, the setting with the smallest worst-case ratio to the best over every scale
    ranked = []
    for op in args.ops:
        score = {}
        for st in settings(grids[op]):
            ratios = []
            for spec in args.taus:
                rs = [r for r in rows if r["op"] == op and r["tau"] == spec]
                best = min(r["ms"] for r in rs)
                mine = [r["ms"] for r in rs if all(r[k] == v for k, v in st.items())]
                ratios.append(mine[0] / best)
            score[tuple(st.items())] = (max(ratios), float(np.mean(ratios)))
        order = sorted(score.items(), key=lambda kv: kv[1])
        ranked += [[op, dict(k), v] for k, v in order]
        print(f"\n{op}: settings by worst ratio to the best (mean ratio):")
        for key, (worst, mean) in order[:6]:
            print(f"  {dict(key)}: worst {worst:.2f}x, mean {mean:.2f}x")
    if args.out:
        Path(args.out).write_text(json.dumps({"mesh": mesh.name, "V": mesh.num_vertices, "device": str(device),
                                              "name": getattr(device, "name", str(device)), "rows": rows,
                                              "ranked": ranked}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
