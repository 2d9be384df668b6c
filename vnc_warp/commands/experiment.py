"""``vnc-warp experiment``: the C-VAE experiment of Sec. 4.3 end to end (flows, dataset, three models,
generation, CD/EMD/NCE against the latent-interpolation baseline, latent anatomy), resumable, in steps."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

HELP = ("run the C-VAE experiment end to end from a preset (cpu-smoke, cpu-rehearsal, gpu) or JSON, whole or one "
        "step at a time: results.json + results.md + PNGs")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--preset", default="cpu-smoke",
                        help="experiment preset (cpu-smoke, cpu-rehearsal, gpu) or a JSON file of overrides with a "
                             "'base' preset")
    parser.add_argument("--out", required=True, metavar="DIR", help="results folder: results.json, results.md, PNGs")
    parser.add_argument("--work", default=None, metavar="DIR",
                        help="folder of trajectories, datasets, checkpoints, predictions; reusing it resumes "
                             "(default: OUT/work, so that re-running the same command resumes)")
    parser.add_argument("--step", type=int, choices=[1, 2, 3, 4], default=None,
                        help="run up to the end of step 1 (data: shapes, flows, dataset), 2 (train C-VAE-I and the "
                             "VAE), 3 (C-VAE-II and generation) or 4 (evaluation, anatomy, results); earlier steps "
                             "are skipped when done (default: all)")
    parser.add_argument("--meshes", default=None, metavar="DIR",
                        help="folder of the real meshes (default: ../shared/data/meshes next to the repository)")
    parser.add_argument("--device", default=None, help="cpu, cuda:0, ... (default: cuda when present)")
    parser.add_argument("--train-budget", type=float, default=None,
                        help="override the seconds of C-VAE-I and, equally, of the VAE (0: none, the configured steps)")
    parser.add_argument("--distill-budget", type=float, default=None,
                        help="override the seconds of C-VAE-II (0: none, the configured steps)")
    parser.add_argument("--max-minutes", type=float, default=None,
                        help="wall-clock minutes of this call (0: none; default: the preset's, 8.5 for gpu): training "
                             "stops with a checkpoint, generation and scoring between predictions and jobs, the "
                             "command exits with status 3 and the same command resumes; flows and the dataset are not "
                             "cut")
    parser.add_argument("--flow-workers", type=int, default=None, help="override the preset's flow processes")
    parser.add_argument("--eval-workers", type=int, default=None, help="override the preset's scoring processes")
    parser.add_argument("--print-config", action="store_true", help="print the resolved config as JSON and exit")


def run(args: argparse.Namespace) -> int:
    from vnc_warp.training.experiment import UNFINISHED_EXIT, load_experiment, run_experiment

    config = load_experiment(args.preset)
    if args.train_budget is not None:
        config.train_budget_s = args.train_budget or None
    if args.distill_budget is not None:
        config.distill_budget_s = args.distill_budget or None
    if args.max_minutes is not None:
        config.max_minutes = args.max_minutes or None
    if args.flow_workers is not None:
        config.flow_workers = args.flow_workers
    if args.eval_workers is not None:
        config.eval_workers = args.eval_workers
    config.validate()
    if args.print_config:
        print(json.dumps(config.to_dict(), indent=1))
        return 0
    work = args.work or str(Path(args.out) / "work")
    results = run_experiment(config, out_dir=args.out, work_dir=work, meshes_dir=args.meshes, device=args.device,
                             progress=not args.no_progress, step=args.step,
                             log=logging.getLogger("vnc_warp").info)
    if "evaluation" not in results:
        print(json.dumps(results, indent=1))
        if results["unfinished"]:
            print(f"step {results['step']} not finished within --max-minutes {config.max_minutes}: "
                  f"{', '.join(results['unfinished'])} left; run the same command again to resume")
            return UNFINISHED_EXIT
        return 0
    print((Path(args.out) / "results.md").read_text())
    failed = sum(row["failed"] for rows in results["evaluation"]["groups"].values() for row in rows.values())
    if failed:
        print(f"{failed} prediction(s) decoded no surface (the 'failed' columns); they are results, not errors")
    return 0
