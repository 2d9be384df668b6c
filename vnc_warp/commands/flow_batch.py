"""``vnc-warp flow-batch``: VNC-Flow over a folder of meshes, sharded across ``torchrun`` processes.

Launch with ``torchrun --nproc_per_node=K -m vnc_warp.cli flow-batch IN OUT`` (or the ``vnc-warp`` script):
rank r of W takes the meshes ``sorted(IN)[r::W]``, one GPU per rank (``cuda:LOCAL_RANK``, modulo the GPUs present)
when there are GPUs and ``--device`` is left out or given as ``cuda``; ``--device cuda:N`` puts every rank on
GPU N. Each mesh's trajectory goes to ``OUT/<file name>/`` (the full name: ``shape.obj`` and ``shape.ply`` get a
folder each), and each mesh ends in one of these states:

* ``done``: computed; ``resumed``: an interrupted trajectory finished; ``skipped``: a finished trajectory with the
  same input and parameters, reused;
* ``refused``: its folder holds a trajectory of other parameters or another input (or files the trajectory does
  not own, or damaged ones), which is left alone; the reason is recorded: use another OUT, or move that folder away;
* ``failed``: the mesh cannot be flowed (unreadable, not a surface, ...); the error is recorded.

The batch goes on after a refused or failed mesh. Every outcome is written to ``OUT/batch.json`` the moment it is
known (one entry per mesh file; entries of earlier runs are kept and the latest outcome replaces a mesh's entry;
the read-modify-write is atomic and locked, so ranks never lose each other's entries), so a rank that dies loses
nothing: the next run skips what was finished and resumes what was under way. A line per mesh and a total are
printed; the exit code is 1 when a mesh of this run failed or was refused.
"""

from __future__ import annotations

import json
import os
import sys
import time
import traceback
from pathlib import Path

from .flow import add_flow_options, flow_kwargs

HELP = "VNC-Flow over a folder of meshes (shards across torchrun ranks; reuses finished ones; batch.json)"
SUFFIXES = (".obj", ".ply", ".off", ".stl", ".glb")
FORMAT = "vnc-warp-batch/1"
RECORD = "batch.json"


def add_arguments(p) -> None:
    p.add_argument("in_dir", help="folder of input meshes")
    p.add_argument("out_dir", help="output folder: one trajectory folder per mesh file, batch.json")
    add_flow_options(p)


def shard(names: list, rank: int, world: int) -> list:
    """The meshes rank ``rank`` of ``world`` processes: a strided split of the sorted names, no overlap."""
    return sorted(names)[rank::world]


def rank_device(device: str | None, local_rank: int) -> str:
    """The Warp device of the rank with ``LOCAL_RANK = local_rank``: ``cuda:<local_rank mod GPUs>`` for ``None`` (when
    there is a GPU, else ``cpu``) and for a bare ``cuda``; any other name as given."""
    import warp as wp

    from vnc_warp._device import init

    init()
    if device is None and not wp.is_cuda_available():
        return "cpu"
    if device is None or device == "cuda":
        count = wp.get_cuda_device_count()
        if count == 0:
            raise ValueError("--device cuda: no CUDA device is available to Warp")
        return f"cuda:{local_rank % count}"
    return device


def read_record(path: Path) -> dict:
    """``batch.json`` (an empty record when absent).

    Raises:
        ValueError: the file exists but is not a flow-batch record (named in the message).
    """
    if not path.exists():
        return {"format": FORMAT, "meshes": []}
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: unreadable flow-batch record ({exc}); move it away to start a new one") from None
    if not isinstance(record, dict) or not isinstance(record.get("meshes"), list) or \
            not all(isinstance(m, dict) and "mesh" in m for m in record["meshes"]):
        raise ValueError(f"{path}: not a flow-batch record (expected an object with a 'meshes' list of entries); "
                         "move it away to start a new one")
    return record


def _store(out_dir: Path, entry: dict, world: int) -> None:
    """Add or replace ``entry`` in ``batch.json``, holding the lock so that concurrent ranks keep each other's."""
    from vnc_warp._files import locked, write_json

    path = out_dir / RECORD
    with locked(out_dir / f".{RECORD}.lock"):
        record = read_record(path)
        meshes = {m["mesh"]: m for m in record["meshes"]}
        meshes[entry["mesh"]] = entry
        record.update(format=FORMAT, world_size=world, meshes=[meshes[k] for k in sorted(meshes)])
        write_json(path, record)


def _finished_stages(folder: Path) -> int:
    """Stages a folder's manifest lists (0 without a readable one); only to tell skipped/resumed/done apart."""
    try:
        return len(json.loads((folder / "manifest.json").read_text()).get("stages", []))
    except (OSError, ValueError, AttributeError):
        return 0


def _flow_one(path: Path, folder: Path, kw: dict) -> dict:
    """Flow one mesh into ``folder``; the outcome as a batch.json entry (never raises for a bad mesh)."""
    from vnc_warp.cli import user_errors
    from vnc_warp.flow import flow
    from vnc_warp.trajectory import TrajectoryError

    before = _finished_stages(folder)
    t0 = time.perf_counter()
    try:
        traj = flow(str(path), out_dir=folder, **kw)
    except TrajectoryError as exc:
        return {"status": "refused", "error": str(exc)}
    except Exception as exc:  # one bad mesh must not end the batch; a bug keeps its traceback on stderr
        if not isinstance(exc, user_errors()):
            traceback.print_exc()
        return {"status": "failed", "error": f"{type(exc).__name__}: {exc}"}
    n = len(traj.meshes)
    status = "skipped" if before == n else "resumed" if before > 0 else "done"
    return {"status": status, "seconds": round(time.perf_counter() - t0, 3), "stages": n - 1,
            "final_t": float(traj.t[-1]), "final_sphericity": traj.records[-1]["sphericity"]}


def _line(entry: dict) -> str:
    if entry["status"] in ("refused", "failed"):
        return f"{entry['mesh']}: {entry['status']}: {entry['error']}"
    return (f"{entry['mesh']}: {entry['status']}, {entry['stages']} stages to t = {entry['final_t']:.4f}, "
            f"sphericity {entry['final_sphericity']:.3f}, {entry['seconds']:.1f} s")


def run(args) -> int:
    from vnc_warp._files import output_dir

    rank = int(os.environ.get("RANK", 0))
    world = int(os.environ.get("WORLD_SIZE", 1))
    local = int(os.environ.get("LOCAL_RANK", 0))
    in_dir, out_dir = Path(args.in_dir), Path(args.out_dir)
    if not in_dir.is_dir():
        raise FileNotFoundError(f"input folder not found: {in_dir}")
    names = sorted(n for n in os.listdir(in_dir) if n.lower().endswith(SUFFIXES) and (in_dir / n).is_file())
    if not names:
        raise ValueError(f"{in_dir}: no mesh files ({', '.join(SUFFIXES)})")
    output_dir(out_dir, what="output folder")
    read_record(out_dir / RECORD)
    kw = flow_kwargs(args)
    kw["device"] = rank_device(kw["device"], local)
    dist = None
    if world > 1:
        import torch.distributed as dist

        dist.init_process_group("gloo")
    prefix = f"[rank {rank}] " if world > 1 else ""
    try:
        for name in shard(names, rank, world):
            entry = {"mesh": name, "folder": name, "rank": rank, "device": kw["device"]}
            entry.update(_flow_one(in_dir / name, out_dir / name, kw))
            entry["finished"] = time.strftime("%Y-%m-%dT%H:%M:%S")
            _store(out_dir, entry, world)
            print(prefix + _line(entry), flush=True)
        if dist is not None:
            dist.barrier()
    except KeyboardInterrupt:
        raise KeyboardInterrupt(f"finished meshes are recorded in {out_dir / RECORD}; run the same command "
                                "again to resume the rest") from None
    finally:
        if dist is not None:
            dist.destroy_process_group()
    entries = {m["mesh"]: m for m in read_record(out_dir / RECORD)["meshes"]}
    mine = [entries[n] for n in names if n in entries]
    counts = {s: sum(m["status"] == s for m in mine) for s in ("done", "resumed", "skipped", "refused", "failed")}
    if rank == 0:
        print(f"flow-batch: {len(names)} mesh(es): " + ", ".join(f"{v} {k}" for k, v in counts.items() if v)
              + f"; {sum(m.get('seconds', 0.0) for m in mine):.1f} s of flow; record: {out_dir / RECORD}",
              file=sys.stdout, flush=True)
    return 1 if counts["refused"] or counts["failed"] else 0
