"""``vnc-warp dataset``: sample VNC-Flow trajectories into a truncated-SDF dataset for the C-VAE."""

from __future__ import annotations

import argparse
import logging
import os

HELP = "sample VNC-Flow trajectories into a truncated-SDF training dataset (one .npz per stage + index.json)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("traj_dirs", nargs="+", metavar="TRAJ_DIR",
                        help="trajectory folders (manifest.json + stages), or folders of them (the OUT_DIR of "
                             "`vnc-warp flow-batch`); files among them (a shell glob's batch.json) are skipped")
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


def trajectory_dirs(paths: list[str]) -> list[str]:
    """The trajectory folders named by ``paths``: a folder with a manifest.json or stage files is one (the loader
    refuses stage files without a manifest); another folder is a folder of them (its subfolders with a manifest,
    sorted); a file is skipped with a note.

    Raises:
        FileNotFoundError: a path that does not exist, or a folder holding no trajectory.
    """
    from vnc_warp.trajectory import stage_files

    out = []
    for p in paths:
        if os.path.isfile(p):
            logging.getLogger("vnc_warp").info("skipping %s: a file, not a trajectory folder", p)
        elif os.path.isfile(os.path.join(p, "manifest.json")) or (os.path.isdir(p) and stage_files(p)):
            out.append(p)
        elif os.path.isdir(p):
            inner = sorted(os.path.join(p, d) for d in os.listdir(p)
                           if os.path.isfile(os.path.join(p, d, "manifest.json")))
            if not inner:
                raise FileNotFoundError(f"{p}: no trajectory folders (a manifest.json in it or its subfolders)")
            out += inner
        else:
            raise FileNotFoundError(f"trajectory folder not found: {p}")
    if not out:
        raise FileNotFoundError(f"no trajectory folders among {' '.join(paths)}")
    return out


def run(args: argparse.Namespace) -> int:
    """Build (and verify) the dataset; errors (an unwritable ``--out``, checked first, trajectory folders with
    foreign or damaged stage files, samples with NaN) reach ``vnc_warp.cli.main`` as one line and exit code 2."""
    from vnc_warp.training.data import build_dataset, verify_dataset

    summary = build_dataset(trajectory_dirs(args.traj_dirs), args.out, num_surface=args.num_surface,
                            num_uniform=args.num_uniform, num_near=args.num_near, noise=args.noise,
                            truncation=args.truncation, device=args.device, seed=args.seed, overwrite=args.overwrite,
                            progress=not args.no_progress)
    print(f"{summary['index']}: {summary['shapes']} shape(s); stages built {summary['built']}, "
          f"rebuilt {summary['rebuilt']}, skipped {summary['skipped']}")
    if args.verify:
        print(f"verified {verify_dataset(args.out)} sample file(s)")
    return 0
