"""``vnc-warp evaluate``: CD / EMD / NCE of generated meshes against a VNC-Flow trajectory (Tab. 2),
optionally next to the latent-interpolation baseline on the same trajectory."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HELP = ("score generated meshes against a ground-truth VNC-Flow trajectory (CD x1e-4, EMD x1e-2, NCE rad; whole and "
        "largest component, beside the sampling floor)")


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
    parser.add_argument("--baseline", default=None, metavar="VAE_RUN",
                        help="also score the latent-interpolation baseline of this plain VAE (a run folder or a "
                             "checkpoint file): it encodes the GT stage 0 and last stage and decodes their linear "
                             "blend at the same times")
    parser.add_argument("--baseline-out", default=None, metavar="DIR",
                        help="folder of the baseline's meshes (default: <PRED>_baseline)")
    parser.add_argument("--resolution", type=int, default=128, help="baseline marching-cubes grid samples per axis")
    parser.add_argument("--device", default=None, help="baseline torch device (default: cuda when present)")


def _print_rows(report: dict) -> None:
    print(f"{'t':>7} {'t_gt':>7} {'stage':>5} {'CD x1e-4':>10} {'EMD x1e-2':>10} {'NCE rad':>8} {'parts':>5} "
          f"{'CD largest':>10} {'CD floor':>9}")
    for e in report["per_t"]:
        if "error" in e:
            print(f"{e['t']:7.4f} {e['t_gt']:7.4f} {e['stage']:5d}  error: {e['error']}")
        else:
            print(f"{e['t']:7.4f} {e['t_gt']:7.4f} {e['stage']:5d} {e['cd_x1e4']:10.3f} {e['emd_x1e2']:10.3f} "
                  f"{e['nce']:8.3f} {e['components']:5d} {e['largest']['cd_x1e4']:10.3f} {e['floor']['cd_x1e4']:9.3f}")
    m = report["mean"]
    print(f"{'mean':>21} {m['cd_x1e4']:10.3f} {m['emd_x1e2']:10.3f} {m['nce']:8.3f} {'':5} "
          f"{m['largest']['cd_x1e4']:10.3f}")


def run(args: argparse.Namespace) -> int:
    from vnc_warp.training.metrics import evaluate_trajectory, read_prediction_dir

    score = dict(n_points=args.n_points, n_emd=args.n_emd, seed=args.seed, oriented=not args.unoriented)
    try:
        preds, meta = read_prediction_dir(args.pred)
        frame = args.pred_frame or meta.get("frame", "world")
        report = evaluate_trajectory(preds, args.gt, pred_frame=frame, **score)
        baseline = None
        if args.baseline is not None:
            from vnc_warp.training.baseline import latent_interpolation
            from vnc_warp.training.checkpoint import load_model
            from vnc_warp.training.train import resolve_device

            model, config = load_model(args.baseline, device=resolve_device(args.device))
            folder = args.baseline_out or f"{str(args.pred).rstrip('/')}_baseline"
            latent_interpolation(model, args.gt, sorted(preds), folder, resolution=args.resolution,
                                 num_surface=config.data.num_surface, seed=args.seed)
            baseline = evaluate_trajectory(read_prediction_dir(folder)[0], args.gt, pred_frame="world", **score)
            baseline.update(pred=folder, checkpoint=str(args.baseline), method="latent_interpolation")
    except ValueError as exc:
        print(f"vnc-warp evaluate: error: {exc}", file=sys.stderr)
        return 2
    report["pred"] = str(args.pred)
    _print_rows(report)
    f = report["sampling_floor"]
    print(f"{'sampling floor':>21} {f['cd_x1e4']:10.3f} {f['emd_x1e2']:10.3f} {f['nce']:8.3f}")
    failed = report["failed"]
    if baseline is not None:
        report["baseline"] = baseline
        failed += baseline["failed"]
        print(f"\nlatent-interpolation baseline ({args.baseline}):")
        _print_rows(baseline)
        print(f"\n{'method':<24} {'CD x1e-4':>10} {'EMD x1e-2':>10} {'NCE rad':>8}   (mean over t)")
        label = meta.get("model_kind") or meta.get("method") or Path(args.pred).name
        for name, rep in ((label, report), ("latent interp. (VAE)", baseline)):
            m = rep["mean"]
            print(f"{name:<24} {m['cd_x1e4']:10.3f} {m['emd_x1e2']:10.3f} {m['nce']:8.3f}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(report, fh, indent=1)
        print(f"report written to {args.out}")
    return 1 if failed else 0
