"""The one trajectory format: a VNC-Flow trajectory (Algorithm 1) in a folder, written, read and resumed here.

A trajectory folder holds one PLY per finished stage and ``manifest.json``::

    {"format": "vnc-warp-trajectory/2", "complete": false, "writing": "stage_003.ply" | null,
     "params": {...}, "source": "koala.obj", "source_digest": "...", "taus": [...], "S_init": ..., ...,
     "stages": [{"index": 0, "t": 1.0, "file": "stage_000.ply", "sha256": "<hex>", ...}, ...]}

Everything besides ``format``, ``complete``, ``writing`` and ``stages`` is the trajectory's ``info``; each entry
of ``stages`` is a stage's record as the flow made it (stored whatever it holds), plus the file's SHA-256.

The rules that keep a user's work safe:

* **The manifest owns the folder's stage files** (``stage_<n>.ply``): the ones it lists, each with its checksum,
  and the one named by ``writing`` (the stage being written when a run stopped; a resumed run overwrites it). A
  folder holding a stage file the manifest does not own (a copy from elsewhere, another run's file), or stage
  files and no manifest, is refused by :meth:`Trajectory.load`, :func:`resume` and :meth:`Trajectory.save`.
* **Checksums are verified** on every load and resume: a listed file that is missing or whose bytes changed
  since it was written is refused, naming the file.
* **Writes are atomic and ordered** (the manifest naming the file as ``writing``, the stage file through a
  temporary file and ``os.replace``, then the manifest listing it), so a run killed at any moment leaves a folder
  these rules accept, and resuming it loses only the stage that was being computed.
* **Older manifests** (``vnc-warp-trajectory/1``, written before checksums existed) are read with a warning that
  their files cannot be verified; resuming one records the checksums of its files as they are. A stage file the
  old writer left unlisted right after the last listed stage (it wrote the file before the manifest) counts as
  the one being written.
"""

from __future__ import annotations

import json
import os
import re
import warnings
from collections.abc import MutableSequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ._files import output_dir, sha256_file, write_json
from .mesh import Mesh, load_mesh

__all__ = ["FORMAT", "LEGACY_FORMATS", "Trajectory", "TrajectoryError", "TrajectoryStage", "budget_summary",
           "read_manifest", "stage_exception",
           "read_trajectory", "resume"]

FORMAT = "vnc-warp-trajectory/2"
LEGACY_FORMATS = ("vnc-warp-trajectory/1",)
MANIFEST = "manifest.json"
_STAGE_FILE = re.compile(r"stage_\d+\.ply")
_OWN_KEYS = ("format", "complete", "writing", "stages")


class TrajectoryError(ValueError):
    """A trajectory folder that cannot be read, resumed or written as asked; the message names the file and why."""


@dataclass(frozen=True)
class TrajectoryStage:
    """One finished stage: stage ``index``, normalized time ``t`` (Eq. (7)), its mesh file and the file's SHA-256
    (None in a manifest older than checksums)."""

    index: int
    t: float
    path: Path
    sha256: str | None = None


class _StageMeshes(MutableSequence):
    """The stage meshes of a folder, each read from its file the first time it is used (a list otherwise: the
    flow appends its new stages)."""

    def __init__(self, loader, count: int):
        self._load = loader
        self._items: list[Mesh | None] = [None] * count

    def __len__(self) -> int:
        return len(self._items)

    def __getitem__(self, i):
        if isinstance(i, slice):
            return [self[k] for k in range(*i.indices(len(self)))]
        k = range(len(self._items))[i]
        if self._items[k] is None:
            self._items[k] = self._load(k)
        return self._items[k]

    def __setitem__(self, i, mesh) -> None:
        self._items[i] = mesh

    def __delitem__(self, i) -> None:
        del self._items[i]

    def insert(self, i, mesh) -> None:
        self._items.insert(i, mesh)


@dataclass
class Trajectory:
    """A VNC-Flow trajectory: meshes, their normalized times and per-stage records.

    Attributes:
        meshes: N+1 meshes; ``meshes[0]`` is the remeshed input (t = 1). Read from a folder, each is loaded from
            its file on first use.
        t: (N+1,) float64 normalized times (Eq. 7), decreasing from 1.
        records: one dict per stage (t, S, iterations, seconds, sphericity, Euler characteristic, status,
            ``history``, ... as the flow records them; ``file`` and ``sha256`` once saved).
        info: trajectory-level facts (params, scales, S_init, phi_stage, source, version, device).
        root: the folder it was read from or last saved to (None: only in memory).
    """

    meshes: Any
    t: np.ndarray
    records: list = field(default_factory=list)
    info: dict = field(default_factory=dict)
    root: Path | None = None

    @property
    def complete(self) -> bool:
        """Whether every one of the ``params["stages"] + 1`` stages is there."""
        return len(self.meshes) == self.info.get("params", {}).get("stages", -1) + 1

    @property
    def name(self) -> str:
        """The folder's name (the shape's name in a dataset), else the source's."""
        return self.root.name if self.root is not None else str(self.info.get("source", ""))

    @property
    def source(self) -> str:
        """The input mesh the flow started from, as recorded."""
        return str(self.info.get("source", ""))

    @property
    def stages(self) -> tuple[TrajectoryStage, ...]:
        """The finished stages' index, t, file and checksum."""
        base = self.root if self.root is not None else Path(".")
        return tuple(TrajectoryStage(int(r["index"]), float(r["t"]), base / r["file"], r.get("sha256"))
                     for r in self.records)

    def load_stage(self, position: int) -> Mesh:
        """The mesh of ``stages[position]``."""
        return self.meshes[position]

    def save(self, out_dir: str | os.PathLike) -> None:
        """Write the stages not yet in ``out_dir`` and the manifest, in the order that survives a kill.

        ``out_dir`` must be empty of trajectories, or the folder this trajectory was read from or saved to.

        Raises:
            TrajectoryError: ``out_dir`` holds another trajectory or stage files that are not this one's.
            OSError: ``out_dir`` cannot be created or written to.
        """
        root = output_dir(out_dir, what="trajectory folder")
        ours = self.root is not None and root.resolve() == Path(self.root).resolve()
        man = _folder_manifest(root)
        if not ours:
            listed = man["stages"] if man is not None else []
            if listed:
                raise TrajectoryError(f"{root / MANIFEST}: the folder already holds a trajectory "
                                      f"({len(listed)} stage(s)); save into an empty folder")
            _check_owned(root, [], man.get("writing") if man is not None else None)
        saved: list[dict] = []
        for k, (rec, mesh) in enumerate(zip(self.records, self.meshes)):
            rec.setdefault("index", k)
            rec.setdefault("file", f"stage_{k:03d}.ply")
            if ours and rec.get("sha256"):
                saved.append(rec)
                continue
            _write_manifest(root, self.info, saved, writing=rec["file"], complete=False)
            path = root / rec["file"]
            tmp = path.with_name(path.name + ".tmp.ply")
            mesh.save(tmp)
            os.replace(tmp, path)
            rec["sha256"] = sha256_file(path)
            saved.append(rec)
        self.root = root
        _write_manifest(root, self.info, saved, writing=None, complete=self.complete)

    @staticmethod
    def load(out_dir: str | os.PathLike) -> "Trajectory":
        """Read a trajectory folder (its finished stages), verifying that the manifest owns its stage files and
        that each listed file matches its checksum; meshes are read when first used.

        Raises:
            FileNotFoundError: no such folder, or neither a manifest nor stage files in it.
            TrajectoryError: anything else that makes the folder unusable (named in the message).
        """
        root = Path(out_dir).resolve()
        if not root.is_dir():
            if root.exists():
                raise TrajectoryError(f"{out_dir} is a file; a trajectory is a folder (manifest.json + stage files)")
            raise FileNotFoundError(f"trajectory folder not found: {out_dir}")
        man = _folder_manifest(root)
        if man is None:
            raise FileNotFoundError(f"no trajectory manifest at {root / MANIFEST}")
        if not man["stages"]:
            raise TrajectoryError(f"{root / MANIFEST}: no finished stages listed (the first stage was still "
                                  "being computed); resume the run to finish it")
        return _trajectory(root, man)


def read_trajectory(traj_dir: str | os.PathLike) -> Trajectory:
    """:meth:`Trajectory.load`; the shape name of a dataset is the folder's name (:attr:`Trajectory.name`)."""
    return Trajectory.load(traj_dir)


def read_manifest(path: str | os.PathLike) -> dict:
    """Read and check a ``manifest.json`` (its structure, not the files it lists).

    Returns:
        The manifest, ``stages`` sorted by index; ``format`` is :data:`FORMAT` or one of :data:`LEGACY_FORMATS`.

    Raises:
        FileNotFoundError: no such file.
        TrajectoryError: unreadable, not JSON, not a trajectory manifest, or malformed stage entries.
    """
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise FileNotFoundError(f"no trajectory manifest at {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise TrajectoryError(f"{path}: cannot read the manifest ({exc})") from None
    try:
        man = json.loads(text)
    except ValueError as exc:
        raise TrajectoryError(f"{path}: not valid JSON ({exc}); the file is damaged or truncated") from None
    if not isinstance(man, dict):
        raise TrajectoryError(f"{path}: a trajectory manifest is a JSON object, this file holds a "
                              f"{type(man).__name__}")
    fmt = man.get("format")
    if fmt != FORMAT and fmt not in LEGACY_FORMATS:
        raise TrajectoryError(f"{path}: format must be {FORMAT!r}, got {fmt!r}")
    stages = man.get("stages")
    if not isinstance(stages, list):
        raise TrajectoryError(f"{path}: 'stages' must be a list, got {type(stages).__name__}")
    for k, st in enumerate(stages):
        if not isinstance(st, dict) or not {"index", "t", "file"} <= st.keys():
            raise TrajectoryError(f"{path}: stages[{k}] needs keys 'index', 't' and 'file', got {st!r}")
        try:
            t, index = float(st["t"]), int(st["index"])
        except (TypeError, ValueError):
            raise TrajectoryError(f"{path}: stages[{k}] has a non-numeric index or t ({st['index']!r}, "
                                  f"{st['t']!r})") from None
        if not np.isfinite(t):
            raise TrajectoryError(f"{path}: stages[{k}] has non-finite t = {st['t']!r}")
        if index < 0:
            raise TrajectoryError(f"{path}: stages[{k}] has a negative index {index}")
        if not isinstance(st["file"], str) or Path(st["file"]).name != st["file"] or st["file"] in ("", ".", ".."):
            raise TrajectoryError(f"{path}: stages[{k}] file must be a file name in the folder, got {st['file']!r}")
        if fmt == FORMAT and not isinstance(st.get("sha256"), str):
            raise TrajectoryError(f"{path}: stages[{k}] has no sha256 checksum")
    stages.sort(key=lambda s: int(s["index"]))
    indices = [int(s["index"]) for s in stages]
    if len(set(indices)) != len(indices):
        raise TrajectoryError(f"{path}: duplicate stage indices {indices}")
    if stages and indices[0] != 0:
        raise TrajectoryError(f"{path}: stage 0 is not listed (stages {indices}); it is the trajectory's input")
    writing = man.get("writing")
    if writing is not None and (not isinstance(writing, str) or Path(writing).name != writing):
        raise TrajectoryError(f"{path}: 'writing' must be a file name in the folder, got {writing!r}")
    return man


def stage_exception(rec: dict, stages: int) -> str | None:
    """Which documented exception of the stage budgets (issue 21) a VNC-Flow stage record is, if any: the last stage
    (t = 0 is below any meshed sphere's VNC-AUC), a stage that did not descend and holds the previous state, a
    topology change by a remesh, the jump of a genus change (or of a part that went) along a bridge, a
    self-intersection the level set joined."""
    if rec["index"] == stages:
        return "last stage"
    if rec.get("status") == "held":
        return "no descent"
    for rm in [rec.get("remesh") or {}] + list(rec.get("remeshes_within") or []):
        if rm and rm.get("euler") != rm.get("euler_in"):
            return "topology change"
    if rec.get("status") == "bridge jump":
        # the jump of a genus change (or a part that went) only: a jump with the topology unchanged is a miss
        # (records from before the bridge recorded it have no "jump_topology" and keep the label)
        if (rec.get("bridge") or {}).get("jump_topology", True):
            return "jump along the bridge"
    if "self-intersection" in (rec.get("exception") or ""):
        return "self-intersection"
    return None


def budget_summary(records: list, stages: int, bound: float = 0.02) -> dict:
    """How a trajectory's stages met their budgets (Eq. 7: stage ``i`` at ``t = 1 - i / N``): ``max_dt`` over every
    stage, ``max_dt_ruled`` with the documented exceptions (:func:`stage_exception`) left out, the ``exceptions``
    by stage index, and the ``misses`` beyond ``bound`` that are no exception, as ``[index, t, target, status]``."""
    dev = [(r, abs(r["t"] - (1.0 - r["index"] / stages))) for r in records if r["index"] > 0]
    exceptions = {r["index"]: e for r, _ in dev if (e := stage_exception(r, stages))}
    ruled = [(r, d) for r, d in dev if r["index"] not in exceptions]
    return {"max_dt": max((d for _, d in dev), default=0.0), "max_dt_ruled": max((d for _, d in ruled), default=0.0),
            "exceptions": exceptions,
            "misses": [[r["index"], r["t"], 1.0 - r["index"] / stages, r.get("status")] for r, d in ruled if d > bound]}


def resume(out_dir: str | os.PathLike, info: dict, *, keys=("params", "source_digest")) -> Trajectory | None:
    """Prepare ``out_dir`` for a run described by ``info``: the trajectory to continue, or None to start afresh.

    Called before anything is computed, so that a folder that cannot be used fails at once.

    Args:
        out_dir: the run's folder (created).
        info: the new run's ``info``; ``info[key]`` must equal the stored run's for every key in ``keys``.
        keys: what makes two runs the same run.

    Returns:
        The stored trajectory (its checksums verified; a legacy manifest is rewritten with checksums), or None
        when the folder holds no finished stage.

    Raises:
        TrajectoryError: the folder holds a different run, files its manifest does not own, or damaged files.
        OSError: the folder cannot be created or written to.
    """
    root = output_dir(out_dir)
    man = _folder_manifest(root)
    if man is None or not man["stages"]:
        return None
    path = root / MANIFEST
    for key in keys:
        if man.get(key) != info.get(key):
            raise TrajectoryError(f"{root} holds a different run ({_difference(key, man.get(key), info.get(key))}); "
                                  "use a new output folder, or delete this one to start over")
    indices = [int(s["index"]) for s in man["stages"]]
    if indices != list(range(len(indices))):
        raise TrajectoryError(f"{path}: stages {indices} are not consecutive from 0; cannot resume")
    traj = _trajectory(root, man)
    if man["format"] != FORMAT:
        for rec, stage in zip(traj.records, traj.stages):
            rec["sha256"] = sha256_file(stage.path)
        _write_manifest(root, traj.info, traj.records, writing=None, complete=traj.complete)
    return traj


def _difference(key: str, stored, new) -> str:
    if isinstance(stored, dict) and isinstance(new, dict):
        diffs = [f"{k}: {stored.get(k)!r} there, {new.get(k)!r} now" for k in sorted(set(stored) | set(new))
                 if stored.get(k) != new.get(k)]
        return f"{key} differ: " + "; ".join(diffs)
    return f"{key} differs: {stored!r} there, {new!r} now"


def stage_files(root: str | os.PathLike) -> list[str]:
    """The names of the stage files (``stage_NNN.ply``) in folder ``root``, sorted."""
    return sorted(n for n in os.listdir(root) if _STAGE_FILE.fullmatch(n))


def _folder_manifest(root: Path) -> dict | None:
    """The folder's checked manifest, None when it has neither manifest nor stage files; refuses stage files that
    the manifest does not own."""
    path = root / MANIFEST
    if not path.exists():
        files = stage_files(root) if root.is_dir() else []
        if files:
            raise TrajectoryError(
                f"{root} holds {len(files)} stage file(s) ({_names(files)}) but no {MANIFEST}: they belong to no "
                "run this folder can continue (a copy, or a run stopped before its first manifest); move them "
                "away or use a new output folder")
        return None
    man = read_manifest(path)
    writing = man.get("writing")
    if man["format"] != FORMAT:
        warnings.warn(f"{path}: a {man['format']} manifest from an older vnc-warp, without checksums: its stage "
                      "files are used as they are, unverified", stacklevel=3)
        n = len(man["stages"])
        leftover = f"stage_{n:03d}.ply"
        if writing is None and (root / leftover).exists():
            writing = leftover  # the old writer wrote a stage's file before listing it
            man["writing"] = writing
    _check_owned(root, [s["file"] for s in man["stages"]], writing)
    return man


def _check_owned(root: Path, listed: list[str], writing: str | None) -> None:
    owned = set(listed) | ({writing} if writing else set())
    stray = [n for n in stage_files(root) if n not in owned]
    if stray:
        raise TrajectoryError(
            f"{root} holds {len(stray)} stage file(s) its {MANIFEST} does not list ({_names(stray)}): they are not "
            "this run's (copied in, or from another run); move them away or use a new output folder")


def _names(files: list[str]) -> str:
    return ", ".join(files[:4]) + (f", ... ({len(files) - 4} more)" if len(files) > 4 else "")


def _trajectory(root: Path, man: dict) -> Trajectory:
    """The trajectory of a checked manifest, after verifying every listed file."""
    path = root / MANIFEST
    for st in man["stages"]:
        file = root / st["file"]
        if not file.is_file():
            raise TrajectoryError(f"{path}: stage {st['index']} lists {st['file']}, which is missing")
        if st.get("sha256") is not None and sha256_file(file) != st["sha256"]:
            raise TrajectoryError(
                f"{file}: does not match its checksum in {MANIFEST} (replaced or damaged after it was written); "
                "restore the file, or move the folder away to compute the trajectory again")
    records = man["stages"]
    info = {k: v for k, v in man.items() if k not in _OWN_KEYS}

    def load(k: int) -> Mesh:
        return load_mesh(root / records[k]["file"], merge=False, name=f"{root.name}/{records[k]['file']}")

    t = np.array([float(r["t"]) for r in records], dtype=np.float64)
    return Trajectory(_StageMeshes(load, len(records)), t, records, info, root)


def _write_manifest(root: Path, info: dict, stages: list, *, writing: str | None, complete: bool) -> None:
    man = dict(info)
    man.update(format=FORMAT, complete=bool(complete), writing=writing, stages=list(stages))
    write_json(root / MANIFEST, man)
