"""``vnc-warp evaluate``: CD / EMD / NCE of generated meshes against a VNC-Flow trajectory (Tab. 2)."""

from __future__ import annotations

import argparse
import json
import sys

HELP = "score generated meshes against a ground-truth VNC-Flow trajectory (CD x1e-4, EMD x1e-2, NCE rad)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--pred", required=True, metavar="DIR", help="output folder of `vnc-warp generate`")
    parser.add_argument("--gt", required=True, metavar="TRAJ_DIR", help="ground-truth trajectory directory")
    parser.add_argument("--out", default=None, metavar="FILE.json", help="write the full report here")
    parser.add_argument("--pred-frame", choices=["world", "normalized"], default=None,
                        help="units of the predictions (default: the listing's 'frame', else world)")
    parser.add_argument("--n-points", type=int, default=100000, help="surface samples for CD and NCE")
    parser.add_argument("--n-emd", type=int, default=4096, help="surface samples for the exact EMD (O(n^3))")
    parser.add_argument("--unoriented", action="store_true", help="unoriented NCE (angle of |n1 . n2|)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed")


def run(args: argparse.Namespace) -> int:
    from vnc_warp.training.metrics import evaluate_trajectory, read_prediction_dir

    try:
        preds, meta = read_prediction_dir(args.pred)
        frame = args.pred_frame or meta.get("frame", "world")
        report = evaluate_trajectory(preds, args.gt, pred_frame=frame, n_points=args.n_points, n_emd=args.n_emd,
                                     seed=args.seed, oriented=not args.unoriented)
    except ValueError as exc:
        print(f"vnc-warp evaluate: error: {exc}", file=sys.stderr)
        return 2
    report["pred"] = str(args.pred)
    print(f"{'t':>7} {'t_gt':>7} {'stage':>5} {'CD x1e-4':>10} {'EMD x1e-2':>10} {'NCE rad':>8}")
    for e in report["per_t"]:
        if "error" in e:
            print(f"{e['t']:7.4f} {e['t_gt']:7.4f} {e['stage']:5d}  error: {e['error']}")
        else:
            print(f"{e['t']:7.4f} {e['t_gt']:7.4f} {e['stage']:5d} {e['cd_x1e4']:10.3f} {e['emd_x1e2']:10.3f} "
                  f"{e['nce']:8.3f}")
    m = report["mean"]
    print(f"{'mean':>21} {m['cd_x1e4']:10.3f} {m['emd_x1e2']:10.3f} {m['nce']:8.3f}")
    f = report["sampling_floor"]
    print(f"{'sampling floor':>21} {f['cd_x1e4']:10.3f} {f['emd_x1e2']:10.3f} {f['nce']:8.3f}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(report, fh, indent=1)
        print(f"report written to {args.out}")
    return 1 if report["failed"] else 0
