"""How the engine's knobs were chosen: VNC-soft and VNC-hard timed over a grid of settings, per scale.

    python -m bench.tune --device cuda:0 --mesh nefertiti.obj --out tune.json
    python -m bench.tune --device cuda:0 --mesh koala.obj --ops hard --set chunk_reach_cuda=6,10,14 --set min_run=4,8

Each setting is a :class:`vnc_warp.tuning.Tuning` (its defaults, with the values of the grid), passed to the operators
as ``tuning=``: every setting runs on an engine of its own (its own kernels, plans and graphs), so nothing is patched
and nothing needs restoring. The grid is the product of the values of every knob given, by its own flag (below) or
as ``--set FIELD=V1,V2`` for any field of ``Tuning``:

* ``--qb``: queries per thread of a busy forward traversal (``qb``);
* ``--busy``: candidates per query from which a traversal counts as busy (``busy_sources``; 0: every one, inf: none);
* ``--splits``: how many ways a box's rows are shared (``splits``; "auto": the rule's choice);
* ``--cell``: grid cell size as a fraction of the typical radius (``cell_fraction``);
* ``--spread``: the per-thread box threshold (``spread``);
* ``--fine``: VNC-hard's Morton bits ordering the records within a cell (``fine_bits``);
* ``--busy-cell``: VNC-hard's cell size in a busy traversal (``busy_ball_cell``);
* ``--ball-kernels``: VNC-hard's kernel variant (``BALL_KERNELS`` below: ``ball_prefilter`` and ``ball_chunks``).

Every setting gives the same sums (the tests check the variants against the BVH); only the time differs. The
table prints the median wall time of a synchronized call per setting and scale, the best setting per scale, and
the settings ranked by their worst ratio to the best.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
from pathlib import Path

import numpy as np

import vnc_warp as vw
from vnc_warp._device import get_device
from vnc_warp.tuning import DEFAULT, Tuning

from .breakdown import _tau, load
from .vnc import measure

# kernel variants of VNC-hard (``kernels.vnc_sums.ball_cells_kernel``): runs of records tested as a whole first
# ("chunks"), the midpoint prefilter; None: chosen per traversal (``_plan.ball_variant``), as in "auto", the default
BALL_KERNELS = {
    "auto": {"ball_prefilter": None, "ball_chunks": None},
    "chords": {"ball_prefilter": None, "ball_chunks": False},
    "chunks": {"ball_prefilter": None, "ball_chunks": True},
    "plain": {"ball_prefilter": False, "ball_chunks": None},
    "prefilter": {"ball_prefilter": True, "ball_chunks": None},
}
FIELDS = {f.name: f for f in dataclasses.fields(Tuning)}


def _value(name: str, text: str):
    """A knob's value from the command line, of the type of its default (``None``/"auto" for optional ones)."""
    if text in ("None", "auto", "none"):
        return None
    default = getattr(DEFAULT, name)
    if isinstance(default, bool):
        return text.lower() in ("1", "true", "yes")
    if isinstance(default, int) and not isinstance(default, bool) and text not in ("inf", "-inf"):
        return int(text)
    if isinstance(default, tuple):
        return tuple(float(v) for v in text.split(":"))
    return float(text)


def settings(grid: dict) -> list[dict]:
    """Every combination of the values of ``grid`` (knob name -> values)."""
    keys = list(grid)
    return [dict(zip(keys, values)) for values in itertools.product(*(grid[k] for k in keys))]


def tuning_of(setting: dict) -> Tuning:
    """The :class:`Tuning` of one setting (``kernel`` names a :data:`BALL_KERNELS` variant)."""
    changes = {k: v for k, v in setting.items() if k != "kernel"}
    if "kernel" in setting:
        changes.update(BALL_KERNELS[setting["kernel"]])
    return DEFAULT.replace(**changes)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--device", default=None)
    ap.add_argument("--mesh", default="nefertiti.obj", help="a file in ../shared/data/meshes or a path")
    ap.add_argument("--subdivide", type=int, default=0, help="midpoint-subdivide the mesh this many times")
    ap.add_argument("--taus", nargs="+", default=["2", "4", "8", "16", "32", "diag/8", "diag/4", "diag/2"])
    ap.add_argument("--ops", nargs="+", default=["soft", "hard"], choices=["soft", "hard"])
    ap.add_argument("--qb", nargs="+", type=int, default=[DEFAULT.qb])
    ap.add_argument("--splits", nargs="+", default=["auto"])
    ap.add_argument("--cell", nargs="+", type=float, default=[DEFAULT.cell_fraction])
    ap.add_argument("--spread", nargs="+", type=float, default=[DEFAULT.spread])
    ap.add_argument("--busy", nargs="+", type=float, default=[DEFAULT.busy_sources])
    ap.add_argument("--fine", nargs="+", type=int, default=[DEFAULT.fine_bits])
    ap.add_argument("--busy-cell", nargs="+", type=float, default=[DEFAULT.busy_ball_cell])
    ap.add_argument("--ball-kernels", nargs="+", default=["auto"], choices=list(BALL_KERNELS))
    ap.add_argument("--set", action="append", default=[], metavar="FIELD=V1,V2",
                    help=f"values of any Tuning field, e.g. --set chunk_reach_cuda=6,10 (fields: {', '.join(FIELDS)})")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    device = get_device(args.device)
    mesh = load(args.mesh, args.subdivide)
    base = {"qb": args.qb, "splits": [None if s == "auto" else int(s) for s in args.splits],
            "cell_fraction": args.cell, "spread": args.spread, "busy_sources": args.busy}
    for item in args.set:
        name, _, values = item.partition("=")
        if name not in FIELDS:
            ap.error(f"--set: {name!r} is not a Tuning field ({', '.join(FIELDS)})")
        base[name] = [_value(name, v) for v in values.split(",")]
    grids = {"soft": dict(base),
             "hard": {**base, "fine_bits": args.fine, "busy_ball_cell": args.busy_cell, "kernel": args.ball_kernels}}
    rows = []
    print(f"{mesh.name}: V={mesh.num_vertices} on {device}")
    for op in args.ops:
        for spec in args.taus:
            tau = _tau(mesh, spec)
            for st in settings(grids[op]):
                tuning = tuning_of(st)
                fn_op = vw.vnc_soft if op == "soft" else vw.vnc_hard
                t = measure(lambda: fn_op(mesh, tau, device=device, tuning=tuning), device, target_s=0.05,
                            max_repeats=args.repeats, min_repeats=3)["median_ms"]
                rows.append({"op": op, "tau": spec, **st, "ms": t})
                print(f"{op:5} {spec:>7} " + " ".join(f"{k}={v}" for k, v in st.items()) + f"  {t:8.3f} ms",
                      flush=True)
    print("\nbest per scale (the default setting's time in brackets):")
    for op in args.ops:
        default = {k: getattr(DEFAULT, k) for k in grids[op] if k != "kernel"}
        if "kernel" in grids[op]:
            default["kernel"] = "auto"
        for spec in args.taus:
            rs = [r for r in rows if r["op"] == op and r["tau"] == spec]
            best = min(rs, key=lambda r: r["ms"])
            d = [r["ms"] for r in rs if all(r[k] == v for k, v in default.items())]
            print(f"{op:5} {spec:>7}: {best['ms']:.3f} ms at "
                  + " ".join(f"{k}={best[k]}" for k in grids[op]) + f"  [{d[0] if d else float('nan'):.3f}]")
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
                                              "ranked": ranked}, indent=1, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
