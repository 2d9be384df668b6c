"""``vnc-warp train``: train the C-VAE (or the plain VecSet VAE) on a trajectory dataset.

Running the same command again resumes the run in ``--out`` (settings compared: see
:mod:`vnc_warp.training.train`); ``--restart`` starts over. Ctrl-C (SIGINT) or SIGTERM writes a checkpoint first.

Several GPUs or nodes: launch through torchrun, e.g.
``torchrun --nproc_per_node=8 -m vnc_warp.cli train --config cvae1 --data DATA --out RUN``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json

HELP = "train the time-conditioned C-VAE (or the plain VecSet VAE) on a trajectory dataset"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True,
                        help="named config (tiny, tiny-vae, tiny-cvae2, cvae1, vae, cvae2) or a JSON file")
    parser.add_argument("--data", required=True, metavar="DATA_DIR",
                        help="dataset folder (index.json, from `vnc-warp dataset`)")
    parser.add_argument("--out", required=True, metavar="RUN_DIR",
                        help="run folder: config.json, log.jsonl, checkpoints/")
    parser.add_argument("--device", default=None, help="torch device (default: cuda when present, else cpu)")
    parser.add_argument("--steps", type=int, default=None, help="override optim.total_steps (schedule length and end)")
    parser.add_argument("--stop-at", type=int, default=None,
                        help="stop after this step, keeping the schedule of total_steps (run again to resume)")
    parser.add_argument("--resume", action="store_true",
                        help="continue exactly from RUN_DIR/checkpoints/last.pt, which must exist (a run folder "
                             "with a checkpoint is resumed anyway: it is never overwritten without --restart)")
    parser.add_argument("--restart", action="store_true",
                        help="discard RUN_DIR's checkpoint and log and train from step 0")
    parser.add_argument("--pretrained", default=None, metavar="RUN",
                        help="C-VAE-II: the plain VAE to freeze, its run folder or a checkpoint file")
    parser.add_argument("--num-workers", type=int, default=None, help="override data.num_workers")


def run(args: argparse.Namespace) -> int:
    from vnc_warp.training.config import load_config
    from vnc_warp.training.train import train

    config = load_config(args.config)
    if args.steps is not None:
        config.optim = dataclasses.replace(config.optim, total_steps=args.steps)
    if args.pretrained is not None:
        config.model = dataclasses.replace(config.model, pretrained=args.pretrained)
    if args.num_workers is not None:
        config.data = dataclasses.replace(config.data, num_workers=args.num_workers)
    summary = train(config, data=args.data, out_dir=args.out, device=args.device, resume=args.resume or None,
                    restart=args.restart, stop_at=args.stop_at, progress=not args.no_progress)
    if summary["rank"] == 0:
        print(json.dumps({k: summary[k] for k in ("step", "checkpoint", "world_size", "samples_per_s", "last")}))
    return 0
