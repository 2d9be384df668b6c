"""``vnc-warp flow-batch``: VNC-Flow over a folder of meshes, sharded across ``torchrun`` processes.

Launch with ``torchrun --nproc_per_node=K -m vnc_warp.cli flow-batch IN OUT`` (or the ``vnc-warp`` script):
rank r of W takes the meshes ``sorted(IN)[r::W]``, one GPU per rank (``cuda:LOCAL_RANK``) when there are
GPUs. Finished trajectories are skipped and interrupted ones resume; rank 0 writes ``OUT/batch.json``.
"""

from __future__ import annotations

import json
import os
import time

from .flow import add_flow_options, flow_kwargs

HELP = "VNC-Flow over a folder of meshes (shards across torchrun ranks; skips finished ones)"
SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb")


def add_arguments(p) -> None:
    p.add_argument("in_dir", help="folder of input meshes")
    p.add_argument("out_dir", help="output folder: one trajectory folder per mesh")
    add_flow_options(p)


def shard(names: list, rank: int, world: int) -> list:
    """The meshes rank ``rank`` of ``world`` processes: a strided split of the sorted names, no overlap."""
    return sorted(names)[rank::world]


def run(args) -> int:
    import warp as wp

    from vnc_warp.flow import Trajectory, flow

    rank = int(os.environ.get("RANK", 0))
    world = int(os.environ.get("WORLD_SIZE", 1))
    local = int(os.environ.get("LOCAL_RANK", 0))
    if not os.path.isdir(args.in_dir):
        raise FileNotFoundError(f"input folder not found: {args.in_dir}")
    names = [n for n in os.listdir(args.in_dir) if n.lower().endswith(SUFFIXES)]
    if not names:
        raise ValueError(f"{args.in_dir}: no mesh files ({', '.join(SUFFIXES)})")
    kw = flow_kwargs(args)
    if kw["device"] is None:
        kw["device"] = f"cuda:{local % wp.get_cuda_device_count()}" if wp.is_cuda_available() else "cpu"
    dist = None
    if world > 1:
        import torch.distributed as dist

        dist.init_process_group("gloo")
    done = []
    for name in shard(names, rank, world):
        out = os.path.join(args.out_dir, os.path.splitext(name)[0])
        if os.path.exists(os.path.join(out, "manifest.json")) and Trajectory.load(out).complete:
            done.append({"mesh": name, "rank": rank, "status": "skipped"})
            continue
        t0 = time.perf_counter()
        traj = flow(os.path.join(args.in_dir, name), out_dir=out, **kw)
        done.append({"mesh": name, "rank": rank, "status": "done", "seconds": time.perf_counter() - t0,
                     "final_t": float(traj.t[-1]), "final_sphericity": traj.records[-1]["sphericity"]})
    results = [done]
    if dist is not None:
        results = [None] * world
        dist.all_gather_object(results, done)
        dist.destroy_process_group()
    if rank == 0:
        os.makedirs(args.out_dir, exist_ok=True)
        with open(os.path.join(args.out_dir, "batch.json"), "w") as fh:
            json.dump({"world_size": world, "meshes": [r for part in results for r in part]}, fh, indent=1)
    return 0
