"""``vnc-warp generate``: predict a mesh's abstraction trajectory with a trained C-VAE."""

from __future__ import annotations

import argparse
import json

HELP = "decode a trained C-VAE at several normalised times t for one input mesh (one mesh per t + JSON)"


def _times(text: str) -> list[float]:
    try:
        return [float(v) for v in text.split(",") if v.strip()]
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"--t expects comma-separated numbers, got {text!r}") from exc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("checkpoint", metavar="RUN",
                        help="a trained model: the run folder of `vnc-warp train --out RUN` (its checkpoints/last.pt) "
                             "or a checkpoint file")
    parser.add_argument("--input", required=True, metavar="MESH", help="detailed input mesh (t = 1), any units")
    parser.add_argument("--t", type=_times, default=[0.0, 0.25, 0.5, 0.75, 1.0], help="comma-separated times in [0, 1]")
    parser.add_argument("--out", required=True, metavar="DIR", help="output folder")
    parser.add_argument("--resolution", type=int, default=128, help="marching-cubes grid samples per axis")
    parser.add_argument("--device", default=None, help="torch device (default: cuda when present, else cpu)")
    parser.add_argument("--num-surface", type=int, default=None, help="encoder surface samples (default: training's)")
    parser.add_argument("--seed", type=int, default=0, help="surface sampling seed")
    parser.add_argument("--format", default="ply", help="mesh file extension (ply, obj, stl, ...)")


def _check_format(extension: str) -> None:
    """Refuse a mesh format trimesh cannot write before anything is decoded."""
    import trimesh

    try:
        trimesh.creation.box().export(file_type=extension)
    except Exception:  # trimesh raises ValueError or KeyError for unknown types
        raise ValueError(f"--format {extension!r}: not a mesh format trimesh can write (ply, obj, stl, off, glb, "
                         "...)") from None


def run(args: argparse.Namespace) -> int:
    from vnc_warp._files import output_dir
    from vnc_warp.training.inference import generate

    _check_format(args.format)
    output_dir(args.out, what="--out")

    report = generate(args.checkpoint, args.input, args.t, args.out, resolution=args.resolution, device=args.device,
                      num_surface=args.num_surface, seed=args.seed, file_format=args.format)
    failed = [e for e in report["meshes"] if e["file"] is None]
    for e in report["meshes"]:
        what = f"{e['file']} ({e['vertices']} vertices)" if e["file"] else f"no mesh: {e['error']}"
        print(f"t={e['t']:.3f}: {what}")
    print(json.dumps({"out": args.out, "written": len(report["meshes"]) - len(failed), "failed": len(failed)}))
    return 1 if failed else 0
