"""Same-machine A/B of two commits' ``bench.vnc`` runs: every row of the base beside the same row of the head.

One run's row moves by up to 4 % between two runs of the same code on one H200 (base 601054e twice at 2094192:
32 l VNC-soft 1.938 then 1.870 ms; the run's first row 0.215 then 0.237 ms), more than the 3 % issue 22 allows a
row to lose. So each side runs more than once, interleaved (base, head, base, head), and a row is compared by the
fastest of its medians on each side: a row counts as slower only where the head's best is above the base's best by
more than :data:`bench.vnc.SLOWER`. Prints the table and writes JSON (``--out``).

    python -m bench.ab --base b1.json b2.json --head h1.json h2.json --out ab.json
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from bench.vnc import SLOWER


def _rows(paths: list[str]) -> tuple[dict, str]:
    """Per ``(mesh, scale, name, variant)`` the medians of the ``ok`` rows of the runs ``paths``, and their device."""
    rows: dict[tuple, list[float]] = {}
    devices = set()
    for path in paths:
        try:
            doc = json.loads(Path(path).read_text())
        except (OSError, ValueError) as exc:
            raise SystemExit(f"bench.ab: cannot read the run {path}: {type(exc).__name__}: {exc}") from exc
        devices.add(doc.get("device", {}).get("name"))
        for r in doc.get("rows", []):
            if r.get("status") == "ok" and r.get("median_ms"):
                rows.setdefault((r["mesh"], r["tau_label"], r["name"], r["variant"]), []).append(r["median_ms"])
    if len(devices) != 1:
        raise SystemExit(f"bench.ab: the runs {paths} come from more than one device: {sorted(map(str, devices))}")
    return rows, devices.pop()


def compare(base: list[str], head: list[str]) -> dict:
    """The rows both sides timed, each with both sides' medians, their best and ``head best / base best``."""
    b, b_dev = _rows(base)
    h, h_dev = _rows(head)
    if b_dev != h_dev:
        raise SystemExit(f"bench.ab: base ran on {b_dev}, head on {h_dev}: not comparable")
    out = []
    for key in b.keys() & h.keys():
        ratio = min(h[key]) / min(b[key])
        out.append({"mesh": key[0], "scale": key[1], "name": key[2], "variant": key[3], "base_ms": b[key],
                    "head_ms": h[key], "ratio": ratio, "slower": ratio > SLOWER})
    out.sort(key=lambda r: (r["mesh"], r["name"], r["variant"], r["scale"]))
    slower = [r for r in out if r["slower"]]
    return {"device": b_dev, "base_runs": base, "head_runs": head, "threshold": SLOWER, "rows": out,
            "compared": len(out), "slower": len(slower), "worst": max((r["ratio"] for r in out), default=None)}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--base", nargs="+", required=True, help="bench.vnc JSON runs of the base commit")
    ap.add_argument("--head", nargs="+", required=True, help="bench.vnc JSON runs of the head commit")
    ap.add_argument("--out", help="write the comparison as JSON here")
    args = ap.parse_args(argv)
    res = compare(args.base, args.head)
    print(f"{'mesh':12s} {'scale':7s} {'row':28s} {'base best':>10s} {'head best':>10s} {'head/base':>9s}")
    for r in res["rows"]:
        mark = "  SLOWER" if r["slower"] else ""
        print(f"{r['mesh'][:12]:12s} {r['scale']:7s} {(r['name'] + '[' + r['variant'] + ']')[:28]:28s} "
              f"{min(r['base_ms']):10.3f} {min(r['head_ms']):10.3f} {r['ratio']:9.3f}{mark}")
    print(f"{res['compared']} rows compared on {res['device']}; {res['slower']} more than "
          f"{100 * (SLOWER - 1):.0f} % slower (best of {len(args.base)} base / {len(args.head)} head runs)")
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    main()
