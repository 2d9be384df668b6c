"""``vnc-warp dataset``: sample VNC-Flow trajectories into a truncated-SDF dataset for the C-VAE."""

from __future__ import annotations

import argparse

HELP = "sample VNC-Flow trajectories into a truncated-SDF training dataset (one .npz per stage + index.json)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("traj_dirs", nargs="+", metavar="TRAJ_DIR", help="trajectory directories (manifest.json + stages)")
    parser.add_argument("--out", required=True, metavar="DATA_DIR", help="dataset directory")
    parser.add_argument("--device", default=None, help="Warp device for the signed distances (default: preferred)")
    parser.add_argument("--num-surface", type=int, default=16384, help="surface points per stage")
    parser.add_argument("--num-uniform", type=int, default=16384, help="uniform queries in [-1, 1]^3 per stage")
    parser.add_argument("--num-near", type=int, default=16384, help="near-surface queries per stage")
    parser.add_argument("--noise", type=float, nargs="+", default=[0.005, 0.02],
                        help="near-surface noise standard deviations (normalized units)")
    parser.add_argument("--truncation", type=float, default=0.1, help="TSDF truncation (normalized units)")
    parser.add_argument("--seed", type=int, default=0, help="sampling seed")
    parser.add_argument("--overwrite", action="store_true", help="rebuild a dataset made with other settings")
    parser.add_argument("--verify", action="store_true", help="check every sample file afterwards")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    """Build (and verify) the dataset; errors (an unwritable ``--out``, checked first, trajectory folders with
    foreign or damaged stage files, samples with NaN) reach ``vnc_warp.cli.main`` as one line and exit code 2."""
    from vnc_warp.training.data import build_dataset, verify_dataset

    summary = build_dataset(args.traj_dirs, args.out, num_surface=args.num_surface, num_uniform=args.num_uniform,
                            num_near=args.num_near, noise=args.noise, truncation=args.truncation,
                            device=args.device, seed=args.seed, overwrite=args.overwrite, progress=not args.quiet)
    print(f"{summary['index']}: {summary['shapes']} shape(s); stages built {summary['built']}, "
          f"rebuilt {summary['rebuilt']}, skipped {summary['skipped']}")
    if args.verify:
        print(f"verified {verify_dataset(args.out)} sample file(s)")
    return 0
