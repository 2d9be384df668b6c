"""The C-VAE experiment of Sec. 4.3 end to end, from procedural shapes to one results table.

:func:`run_experiment` runs, in order, each stage skipped when its output is already there (an
interrupted run continues where it stopped):

1. **shapes**: procedural genus-0 shapes (:func:`vnc_warp.shapes.shape_family`) written as PLY, and
   the real meshes named by the config, read from a folder (nothing is downloaded);
2. **flows**: one VNC-Flow trajectory per shape (Algorithm 1, :func:`vnc_warp.flow.flow` with
   ``out_dir``, resumable), in a pool of processes when ``flow_workers > 1``;
3. **dataset**: truncated-SDF samples of the training trajectories (:func:`~vnc_warp.training.data.build_dataset`);
4. **training**: C-VAE-I on the procedural and real training shapes; the plain VecSet VAE of the same
   size on the same shapes (every stage auto-encoded); C-VAE-II on one real trajectory (distillation)
   on top of the frozen VAE encoder. With ``time_budget_s`` the step counts come from a measured
   throughput (a short calibration run) so the whole experiment fits the budget;
5. **generation**: meshes at ``times`` from the held-out shapes' stage 0 (C-VAE-I), from the
   distilled shape (C-VAE-II, C-VAE-I) and from the latent-interpolation baseline
   (:mod:`vnc_warp.training.baseline`) on the same trajectories;
6. **evaluation**: CD / EMD / NCE (Tab. 2, :func:`~vnc_warp.training.metrics.evaluate_trajectory`)
   of every prediction against the ground-truth stage nearest in t;
7. **latent anatomy** (Fig. 11): C-VAE-I latents of every stage of the held-out trajectories, PCA of
   the mean-pooled latents (UMAP of the max-pooled ones when umap-learn is installed), their
   correlations with t; the plain VAE's latents of the same stages as a control;
8. **results**: ``results.json`` and ``results.md`` (tables) and a few PNGs in ``out_dir``;
   trajectories, datasets, checkpoints and predicted meshes stay in ``work_dir``.

Sizes come from an :class:`ExperimentConfig`; :data:`PRESETS` holds ``cpu-smoke`` (minutes on a
2-core CPU) and ``gpu`` (one H200, about 8 minutes of wall time including the flows).
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import json
import math
import multiprocessing
import os
import platform
import time
import typing
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from .config import DataConfig, LossConfig, ModelConfig, OptimConfig, TrainConfig, _from_dict

__all__ = ["ExperimentConfig", "PRESETS", "preset", "load_experiment", "run_experiment", "default_meshes_dir",
           "results_markdown"]

METHODS = {"cvae1": "C-VAE-I", "cvae2": "C-VAE-II", "baseline": "latent interp. (VAE)"}
_SHORT = {"cvae1": "C-VAE-I", "cvae2": "C-VAE-II", "baseline": "interp."}
MODELS = {"cvae1": "C-VAE-I", "vae": "VAE (baseline; C-VAE-II's frozen encoder)", "cvae2": "C-VAE-II"}
# settings that change how fast a run goes, not what it computes: a work folder may be resumed with others
_RUNTIME_KEYS = ("name", "flow_workers", "flow_budget_s", "eval_workers", "torch_threads", "figures", "time_budget_s",
                 "reserve_s", "train_shares", "render_size")


@dataclass
class ExperimentConfig:
    """Everything :func:`run_experiment` needs besides the folders and the device.

    Attributes:
        name: label (the preset's name).
        num_shapes: procedural shapes (:func:`vnc_warp.shapes.shape_family`).
        shape_seed: family seed.
        subdivisions: icosphere subdivisions of the procedural shapes (3: 642 vertices, 4: 2562).
        holdout_shapes: the last this many procedural shapes are held out (never trained on).
        train_meshes: real mesh files (in the meshes folder) added to the training set.
        holdout_meshes: real mesh files held out (generalization, latent anatomy).
        distill_mesh: the training mesh C-VAE-II distils (Sec. 4.3); ``""`` skips C-VAE-II.
        real_faces: face count of the real meshes' remeshed states (their flows' ``faces``).
        real_resolution: SDF-remesh grid nodes for the real meshes (None: automatic).
        stages: VNC-Flow stages N.
        max_iters: VNC-Flow iteration cap per stage.
        flow_workers: processes running flows at once (1: in this process).
        flow_budget_s: seconds after which procedural training shapes whose flow has not started are
            left out (held-out and real shapes always flow, first); None: no limit.
        num_samples: surface points, uniform and near-surface queries per stage of the dataset.
        truncation: TSDF truncation (normalized units).
        backbone: the VecSet backbone shared by all three models (``kind`` and ``pretrained`` are set
            per model): the baseline VAE is the C-VAE's size by construction.
        cvae1, vae, cvae2: training configurations; their ``model`` sections are replaced by
            ``backbone`` and their ``data.encoder_input`` by the model's (stage 0 for the C-VAEs, the
            item itself for the VAE). ``optim.total_steps`` is the step count, or the cap with a budget.
        repeats: passes over the training stages per data-loader epoch.
        distill_repeats: the same for the single distilled trajectory.
        time_budget_s: wall-clock budget of the whole experiment; None trains the configured steps.
        reserve_s: seconds of the budget kept for generation, evaluation and figures.
        train_shares: shares of the training time of C-VAE-I, VAE and C-VAE-II.
        calibration_steps: steps timed before the step count of a budgeted model is fixed.
        min_steps: fewest steps of a budgeted model.
        torch_threads: torch CPU threads while training (None: torch's default).
        times: normalized times the models are decoded at.
        resolution: marching-cubes grid samples per axis.
        n_points, n_emd: surface samples for CD/NCE and for the exact EMD.
        eval_workers: processes scoring predictions at once.
        figures: write the trajectory montages.
        render_size: pixels per montage frame.
        seed: seed of the evaluation and anatomy sampling.
    """

    name: str = "custom"
    num_shapes: int = 6
    shape_seed: int = 0
    subdivisions: int = 3
    holdout_shapes: int = 1
    train_meshes: tuple[str, ...] = ("spot_lowres.obj", "human_man.obj")
    holdout_meshes: tuple[str, ...] = ("fandisk.obj",)
    distill_mesh: str = "human_man.obj"
    real_faces: int = 1280
    real_resolution: int | None = 40
    stages: int = 3
    max_iters: int = 300
    flow_workers: int = 1
    flow_budget_s: float | None = None
    num_samples: tuple[int, int, int] = (2048, 2048, 2048)
    truncation: float = 0.1
    backbone: ModelConfig = field(default_factory=ModelConfig)
    cvae1: TrainConfig = field(default_factory=TrainConfig)
    vae: TrainConfig = field(default_factory=TrainConfig)
    cvae2: TrainConfig = field(default_factory=TrainConfig)
    repeats: int = 1
    distill_repeats: int = 4
    time_budget_s: float | None = None
    reserve_s: float = 60.0
    train_shares: tuple[float, float, float] = (0.45, 0.3, 0.25)
    calibration_steps: int = 30
    min_steps: int = 100
    torch_threads: int | None = None
    times: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0)
    resolution: int = 48
    n_points: int = 5000
    n_emd: int = 500
    eval_workers: int = 1
    figures: bool = True
    render_size: int = 160
    seed: int = 0

    def to_dict(self) -> dict[str, Any]:
        """Nested dict of primitives (JSON-safe)."""
        return json.loads(json.dumps(dataclasses.asdict(self)))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "ExperimentConfig":
        """Build and validate a config; missing keys take the defaults, unknown keys are errors."""
        data = dict(data)
        for key, hint in typing.get_type_hints(cls).items():
            if typing.get_origin(hint) is tuple and isinstance(data.get(key), list):
                data[key] = tuple(data[key])
        sections = {k: data.pop(k) for k in ("cvae1", "vae", "cvae2") if k in data}
        backbone = data.pop("backbone", None)
        unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
        if unknown:
            raise ValueError(f"unknown experiment key(s) {unknown}")
        cfg = cls(**data)
        if backbone is not None:
            cfg.backbone = _from_dict(ModelConfig, backbone, "backbone.")
        for key, value in sections.items():
            setattr(cfg, key, TrainConfig.from_dict(value))
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Check what would fail deep inside a run.

        Raises:
            ValueError: naming the key and the value.
        """
        if self.num_shapes < 1 or not 0 <= self.holdout_shapes < self.num_shapes:
            raise ValueError(f"need num_shapes >= 1 and 0 <= holdout_shapes < num_shapes, got {self.num_shapes} "
                             f"and {self.holdout_shapes}")
        if not self.holdout_shapes and not self.holdout_meshes:
            raise ValueError("nothing is held out: set holdout_shapes > 0 or list holdout_meshes")
        if self.distill_mesh and self.distill_mesh not in self.train_meshes:
            raise ValueError(f"distill_mesh {self.distill_mesh!r} must be one of train_meshes "
                             f"{list(self.train_meshes)}")
        names = [Path(m).stem for m in (*self.train_meshes, *self.holdout_meshes)]
        if len(set(names)) != len(names):
            raise ValueError(f"real mesh names must be unique (train and held out together), got {names}")
        if self.stages < 1 or self.max_iters < 1 or self.flow_workers < 1 or self.eval_workers < 1:
            raise ValueError("stages, max_iters, flow_workers and eval_workers must be >= 1")
        if min(self.num_samples) < 1 or self.repeats < 1 or self.distill_repeats < 1:
            raise ValueError("num_samples, repeats and distill_repeats must be >= 1")
        if not self.times or not all(0.0 <= t <= 1.0 for t in self.times):
            raise ValueError(f"times must be a non-empty list in [0, 1], got {list(self.times)}")
        if self.flow_budget_s is not None and not self.flow_budget_s > 0:
            raise ValueError(f"flow_budget_s must be positive or None, got {self.flow_budget_s}")
        if self.time_budget_s is not None and not self.time_budget_s > 0:
            raise ValueError(f"time_budget_s must be positive or None, got {self.time_budget_s}")
        if len(self.train_shares) != 3 or min(self.train_shares) <= 0:
            raise ValueError(f"train_shares must be three positive numbers, got {self.train_shares}")
        if not 1 <= self.n_emd <= self.n_points or self.resolution < 8:
            raise ValueError("need 1 <= n_emd <= n_points and resolution >= 8")
        for kind in ("cvae1", "vae", "cvae2"):
            run_config(self, kind, pretrained="vae.pt").validate()


def run_config(config: ExperimentConfig, kind: str, *, pretrained: str | None = None) -> TrainConfig:
    """The training configuration of model ``kind`` (``cvae1``, ``vae``, ``cvae2``): its section of
    ``config`` with the shared backbone and the model's encoder input."""
    section = getattr(config, kind)
    cfg = TrainConfig.from_dict(section.to_dict())
    cfg.model = dataclasses.replace(config.backbone, kind=kind, pretrained=pretrained if kind == "cvae2" else None)
    cfg.data = dataclasses.replace(cfg.data, encoder_input="item" if kind == "vae" else "stage0")
    cfg.name = f"{config.name}-{kind}"
    return cfg


def _train_section(*, lr: float, steps: int, warmup: int, batch: int, surface: int, queries: int, workers: int,
                   kl: float, linear_kl: bool, eik_queries: int, log_every: int, ckpt_every: int) -> TrainConfig:
    loss = LossConfig(kl_weight=kl, kl_schedule="linear" if linear_kl else "constant", kl_weight_start=0.0,
                      kl_warmup_start=steps // 10 if linear_kl else 0, kl_warmup_steps=steps // 2 if linear_kl else 0,
                      eikonal_weight=0.01, eikonal_queries=eik_queries)
    return TrainConfig(loss=loss, optim=OptimConfig(lr=lr, weight_decay=0.01, warmup_steps=warmup, total_steps=steps,
                                                    min_lr_ratio=0.1),
                       data=DataConfig(num_surface=surface, num_queries=queries, batch_size=batch, num_workers=workers),
                       bf16=True, log_every=log_every, ckpt_every=ckpt_every)


def _cpu_smoke() -> ExperimentConfig:
    """About 2 minutes on a 2-core CPU: 6 shapes of 642 vertices (one held out), Spot and the SMPL body
    remeshed to 1280 faces for training, fandisk held out, 3 stages, ~0.3M-parameter models, fixed steps."""
    small = dict(batch=4, surface=256, queries=256, workers=0, eik_queries=64, log_every=10, ckpt_every=100)
    return ExperimentConfig(
        name="cpu-smoke", num_shapes=6, shape_seed=0, subdivisions=3, holdout_shapes=1,
        train_meshes=("spot_lowres.obj", "human_man.obj"), holdout_meshes=("fandisk.obj",),
        distill_mesh="human_man.obj",
        real_faces=1280, real_resolution=40, stages=3, max_iters=200, flow_workers=1, num_samples=(2048, 2048, 2048),
        backbone=ModelConfig(width=64, heads=4, num_latents=32, latent_dim=8, encoder_depth=1, decoder_depth=2,
                             num_freqs=6, chunk_size=16384, time_tokens=2, time_freq_dim=64, modulator_depth=1),
        cvae1=_train_section(lr=1e-3, steps=500, warmup=20, kl=1e-4, linear_kl=True, **small),
        vae=_train_section(lr=1e-3, steps=500, warmup=20, kl=1e-4, linear_kl=False, **small),
        cvae2=_train_section(lr=1e-3, steps=300, warmup=20, kl=1e-4, linear_kl=False, **small),
        repeats=1, distill_repeats=4, time_budget_s=None, torch_threads=1, resolution=48, n_points=5000, n_emd=500,
        eval_workers=1, figures=True, render_size=128)


def _gpu() -> ExperimentConfig:
    """One H200, about 8 minutes of wall time including the flows.

    48 shapes of 2562 vertices (6 held out) and Spot, bunny, armadillo and the SMPL body remeshed to
    6000 faces for training, fandisk and FAUST held out, 8 stages, flows in 8 processes (held-out and
    real shapes first; procedural training shapes not started after 180 s are left out). The paper's
    models (2048 x 32/64 latents, 768/1024 wide, 16-24 layers) would get a few hundred steps in this
    budget; these are 384 wide with 512 x 32 latents and 2 + 6 layers (C-VAE-I 24M parameters, the
    VAE 18M), trained in bf16 for as many steps as the budget allows (calibrated), at most
    8000 / 8000 / 4000.
    """
    big = dict(batch=32, surface=4096, queries=4096, workers=6, eik_queries=1024, log_every=10, ckpt_every=500)
    return ExperimentConfig(
        name="gpu", num_shapes=48, shape_seed=0, subdivisions=4, holdout_shapes=6,
        train_meshes=("spot_lowres.obj", "bunny.obj", "armadillo.obj", "human_man.obj"),
        holdout_meshes=("fandisk.obj", "faust_tr_reg_025.ply"), distill_mesh="human_man.obj",
        real_faces=6000, real_resolution=None, stages=8, max_iters=300, flow_workers=8, flow_budget_s=180.0,
        num_samples=(8192, 8192, 8192),
        backbone=ModelConfig(width=384, heads=6, num_latents=512, latent_dim=32, encoder_depth=2, decoder_depth=6,
                             num_freqs=8, chunk_size=32768, time_tokens=4, time_freq_dim=256, modulator_depth=2),
        cvae1=_train_section(lr=3e-4, steps=8000, warmup=200, kl=1e-3, linear_kl=True, **big),
        vae=_train_section(lr=3e-4, steps=8000, warmup=200, kl=1e-3, linear_kl=False, **big),
        cvae2=_train_section(lr=2e-4, steps=4000, warmup=100, kl=1e-4, linear_kl=False, **big),
        repeats=8, distill_repeats=64, time_budget_s=420.0, reserve_s=100.0, train_shares=(0.45, 0.3, 0.25),
        calibration_steps=30, min_steps=100, torch_threads=None, resolution=96, n_points=20000, n_emd=1024,
        eval_workers=8, figures=True, render_size=192)


PRESETS: dict[str, Callable[[], ExperimentConfig]] = {"cpu-smoke": _cpu_smoke, "gpu": _gpu}


def preset(name: str) -> ExperimentConfig:
    """A fresh copy of a named experiment (``cpu-smoke`` or ``gpu``).

    Raises:
        ValueError: unknown name.
    """
    if name not in PRESETS:
        raise ValueError(f"unknown experiment preset {name!r}; presets: {', '.join(PRESETS)}")
    return PRESETS[name]()


def _merge(base: dict, override: dict) -> dict:
    out = dict(base)
    for key, value in override.items():
        out[key] = _merge(out[key], value) if isinstance(value, dict) and isinstance(out.get(key), dict) else value
    return out


def load_experiment(name_or_path: str | os.PathLike) -> ExperimentConfig:
    """A preset, or a JSON file of overrides (nested, partial) on top of the preset named by its
    ``"base"`` key (default ``cpu-smoke``).

    Raises:
        FileNotFoundError: neither a preset nor a file.
        ValueError: unreadable JSON or invalid content.
    """
    text = os.fspath(name_or_path)
    if text in PRESETS:
        return preset(text)
    path = Path(text)
    if not path.is_file():
        raise FileNotFoundError(f"experiment {text!r} is neither a preset ({', '.join(PRESETS)}) nor a JSON file")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: cannot read experiment JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise ValueError(f"{path}: the experiment JSON must be an object")
    base = preset(data.pop("base", "cpu-smoke"))
    try:
        return ExperimentConfig.from_dict(_merge(base.to_dict(), data))
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc


def default_meshes_dir() -> Path | None:
    """``../shared/data/meshes`` next to the repository, when it exists."""
    path = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "meshes"
    return path if path.is_dir() else None


class _Clock:
    """Wall time per stage and the experiment's deadline."""

    def __init__(self, budget_s: float | None) -> None:
        self.start = time.perf_counter()
        self.deadline = None if budget_s is None else self.start + budget_s
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str, log: Callable[[str], None]) -> Iterator[None]:
        log(f"[experiment] {name} ...")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - t0
            log(f"[experiment] {name}: {self.seconds[name]:.1f} s")

    def left(self) -> float | None:
        return None if self.deadline is None else self.deadline - time.perf_counter()

    def total(self) -> float:
        return time.perf_counter() - self.start


@dataclass
class _Shape:
    name: str
    source: Path
    kind: str  # "procedural" | "real"
    role: str  # "train" | "holdout"
    faces: int | None
    resolution: int | None
    traj: Path
    status: str = "pending"
    info: dict = field(default_factory=dict)


def _check_work_dir(work: Path, config: ExperimentConfig) -> None:
    """A work folder belongs to one experiment: refuse one made with other sizes (stale outputs)."""
    stamp = work / "experiment.json"
    key = {k: v for k, v in config.to_dict().items() if k not in _RUNTIME_KEYS}
    if stamp.is_file():
        old = json.loads(stamp.read_text())
        if old != key:
            diff = sorted(k for k in set(old) | set(key) if old.get(k) != key.get(k))
            raise ValueError(f"{work} holds an experiment with other settings ({', '.join(diff)} differ); "
                             "use another --work folder")
        return
    work.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(key, indent=1))


def _shapes(config: ExperimentConfig, work: Path, meshes_dir: Path | None) -> list[_Shape]:
    from vnc_warp.shapes import shape_family

    real = [*config.train_meshes, *config.holdout_meshes]
    if real:
        if meshes_dir is None or not meshes_dir.is_dir():
            raise FileNotFoundError(f"the experiment needs real meshes {real}: pass their folder (--meshes DIR); "
                                    f"{meshes_dir} is not a folder")
        missing = [m for m in real if not (meshes_dir / m).is_file()]
        if missing:
            raise FileNotFoundError(f"{meshes_dir}: missing mesh file(s) {missing}")
    shapes = []
    folder = work / "shapes"
    folder.mkdir(parents=True, exist_ok=True)
    family = None
    for i in range(config.num_shapes):
        name = f"family{config.shape_seed}_{i:04d}"
        path = folder / f"{name}.ply"
        if not path.is_file():
            if family is None:
                family = shape_family(config.num_shapes, config.shape_seed, subdivisions=config.subdivisions)
            tmp = folder / f"{name}.tmp.ply"
            family[i].save(tmp)
            os.replace(tmp, path)
        role = "holdout" if i >= config.num_shapes - config.holdout_shapes else "train"
        shapes.append(_Shape(name, path, "procedural", role, None, None, work / "traj" / name))
    for files, role in ((config.train_meshes, "train"), (config.holdout_meshes, "holdout")):
        for file in files:
            name = Path(file).stem
            shapes.append(_Shape(name, (meshes_dir / file).resolve(), "real", role, config.real_faces,
                                 config.real_resolution, work / "traj" / name))
    return shapes


def _flow_job(job: dict) -> dict:
    """Run (or resume) one VNC-Flow; module-level so that a process pool can pickle it."""
    import vnc_warp._device  # noqa: F401  (quiet Warp first)
    from vnc_warp.flow import flow

    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            traj = flow(job["source"], stages=job["stages"], faces=job["faces"], device=job["device"],
                        out_dir=job["out_dir"], progress=False, resolution=job["resolution"],
                        max_iters=job["max_iters"])
    except Exception as exc:  # one failed shape must not end the experiment; it is reported
        return {"name": job["name"], "status": "failed", "error": f"{type(exc).__name__}: {exc}",
                "seconds": time.perf_counter() - t0}
    return {"name": job["name"], "status": "done", "seconds": time.perf_counter() - t0, "stages": len(traj.t) - 1,
            "t": [round(float(t), 4) for t in traj.t], "final_sphericity": traj.records[-1]["sphericity"],
            "vertices": traj.meshes[0].num_vertices, "warnings": len(caught)}


def _complete(traj_dir: Path, stages: int) -> bool:
    man = traj_dir / "manifest.json"
    if not man.is_file():
        return False
    try:
        data = json.loads(man.read_text())
    except (OSError, ValueError):
        return False
    return bool(data.get("complete")) and len(data.get("stages", [])) == stages + 1


def _flows(shapes: list[_Shape], config: ExperimentConfig, device: str | None, work: Path,
           log: Callable[[str], None]) -> None:
    """Run the missing flows; held-out and real shapes first, so a flow budget only ever drops
    procedural training shapes (listed in ``work/dropped.json`` and left out of every later run too)."""
    dropped_path = work / "dropped.json"
    dropped = set(json.loads(dropped_path.read_text())) if dropped_path.is_file() else set()
    jobs = []
    for s in sorted(shapes, key=lambda s: s.kind == "procedural" and s.role == "train"):
        if s.name in dropped:
            s.status, s.info = "dropped", {"status": "dropped (flow budget of an earlier run)"}
        elif _complete(s.traj, config.stages):
            man = json.loads((s.traj / "manifest.json").read_text())
            s.status, s.info = "done", {"status": "skipped (done)", "t": [round(r["t"], 4) for r in man["stages"]]}
        else:
            jobs.append({"name": s.name, "source": str(s.source), "stages": config.stages, "faces": s.faces,
                         "resolution": s.resolution, "max_iters": config.max_iters, "device": device,
                         "out_dir": str(s.traj), "optional": s.kind == "procedural" and s.role == "train"})
    by_name = {s.name: s for s in shapes}
    t0 = time.perf_counter()

    def record(res: dict) -> None:
        s = by_name[res["name"]]
        s.status, s.info = res["status"], res
        log(f"  flow {res['name']}: {res['status']} in {res['seconds']:.1f} s"
            + (f" ({res['error']})" if "error" in res else f", t = {res['t']}"))

    def over_budget() -> bool:
        return config.flow_budget_s is not None and time.perf_counter() - t0 > config.flow_budget_s

    def drop(job: dict) -> None:
        by_name[job["name"]].status = "dropped"
        by_name[job["name"]].info = {"status": f"dropped (flow budget {config.flow_budget_s} s)"}
        dropped.add(job["name"])
        dropped_path.write_text(json.dumps(sorted(dropped)))

    if not jobs:
        return
    # The first flow runs here: it compiles every Warp kernel into the cache the pool then reuses.
    record(_flow_job(jobs[0]))
    rest = jobs[1:]
    if config.flow_workers == 1 or not rest:
        for job in rest:
            if job["optional"] and over_budget():
                drop(job)
            else:
                record(_flow_job(job))
        return
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=min(config.flow_workers, len(rest)), mp_context=ctx) as pool:
        futures = {pool.submit(_flow_job, job): job for job in rest}
        for fut in cf.as_completed(futures):
            if fut.cancelled():
                continue
            record(fut.result())
            if over_budget():
                for other, job in futures.items():
                    if job["optional"] and other.cancel():
                        drop(job)


def _last_step(run: Path) -> int:
    from .checkpoint import load_checkpoint

    ckpt = run / "checkpoints" / "last.pt"
    return int(load_checkpoint(ckpt)["step"]) if ckpt.is_file() else 0


def _scaled(cfg: TrainConfig, total: int) -> TrainConfig:
    """``cfg`` with ``total`` steps; warm-ups given for its nominal length scale with it."""
    ratio = total / cfg.optim.total_steps
    cfg.optim = dataclasses.replace(cfg.optim, total_steps=total,
                                    warmup_steps=max(1, round(cfg.optim.warmup_steps * ratio)))
    cfg.loss = dataclasses.replace(cfg.loss, kl_warmup_start=round(cfg.loss.kl_warmup_start * ratio),
                                   kl_warmup_steps=round(cfg.loss.kl_warmup_steps * ratio))
    return cfg


def _rows(run: Path) -> list[dict]:
    path = run / "log.jsonl"
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.is_file() else []


def _train(kind: str, cfg: TrainConfig, dataset, run: Path, *, device: str | None, budget_s: float | None,
           config: ExperimentConfig, progress: bool, log: Callable[[str], None]) -> dict:
    """Train one model to its planned step count (resuming, or skipping when done) and summarize it."""
    from .train import train

    run.mkdir(parents=True, exist_ok=True)
    plan_path = run / "plan.json"
    seconds = 0.0
    if plan_path.is_file():
        plan = json.loads(plan_path.read_text())
    else:
        plan = {"nominal_steps": cfg.optim.total_steps, "budget_s": budget_s}
        total = cfg.optim.total_steps
        if budget_s is not None:
            calib = min(config.calibration_steps, total)
            t0 = time.perf_counter()
            train(cfg, data=dataset, out_dir=run, device=device, resume=_last_step(run) > 0, stop_at=calib,
                  progress=progress)
            seconds += time.perf_counter() - t0
            rows = _rows(run)
            # windows after the first (CUDA start-up, first batches) when there are several
            timed = rows[1:] or rows
            rates = [r["samples_per_s"] / cfg.data.batch_size for r in timed] or [calib / seconds]
            rate = float(np.median(rates))
            # 0.9: checkpoints and data-loader restarts fall between the timed windows
            total = int(np.clip(calib + 0.9 * rate * max(budget_s - seconds, 0.0), config.min_steps, total))
            plan.update(calibration_steps=calib, calibration_seconds=seconds, steps_per_s=rate)
        plan["total_steps"] = total
        plan_path.write_text(json.dumps(plan, indent=1))
    cfg = _scaled(cfg, plan["total_steps"])
    done = _last_step(run)
    if done < cfg.optim.total_steps:
        log(f"  {kind}: training to step {cfg.optim.total_steps} (from {done}), budget "
            f"{'none' if budget_s is None else f'{budget_s:.0f} s'}")
        t0 = time.perf_counter()
        train(cfg, data=dataset, out_dir=run, device=device, resume=done > 0, progress=progress)
        seconds += time.perf_counter() - t0
    plan["seconds"] = plan.get("seconds", 0.0) + seconds
    plan_path.write_text(json.dumps(plan, indent=1))
    rows = _rows(run)
    steady = [r["samples_per_s"] for r in rows[1:]] or [r["samples_per_s"] for r in rows]
    last = rows[-1] if rows else {}
    return {"steps": cfg.optim.total_steps, "batch_size": cfg.data.batch_size, "seconds": plan["seconds"],
            "samples_per_s": cfg.optim.total_steps * cfg.data.batch_size / max(plan["seconds"], 1e-9),
            "steady_samples_per_s": float(np.median(steady)) if steady else math.nan,
            "final": {k: last.get(k) for k in ("loss", "tsdf", "kl", "eik", "beta_kl")},
            "budget_s": plan.get("budget_s"), "items": len(dataset)}


def _budget(clock: _Clock, config: ExperimentConfig, shares: list[float]) -> float | None:
    """Seconds for the next model: its share of what is left after the generation reserve."""
    left = clock.left()
    if left is None:
        return None
    return max(left - config.reserve_s, 0.0) * shares[0] / sum(shares)


def _param_count(model: torch.nn.Module) -> dict[str, int]:
    return {"total": sum(p.numel() for p in model.parameters()),
            "trainable": sum(p.numel() for p in model.parameters() if p.requires_grad)}


def _eval_job(job: dict) -> dict:
    """Score one prediction folder against its trajectory; module-level for the process pool."""
    from .metrics import evaluate_trajectory, read_prediction_dir

    preds, _ = read_prediction_dir(job["pred"])
    report = evaluate_trajectory(preds, job["gt"], pred_frame="world", n_points=job["n_points"], n_emd=job["n_emd"],
                                 seed=job["seed"])
    tmp = Path(job["out"] + ".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, job["out"])
    return report


def _predicted(folder: Path, times: tuple[float, ...]) -> bool:
    listing = folder / "generate.json"
    if not listing.is_file():
        return False
    try:
        got = sorted(e["t"] for e in json.loads(listing.read_text())["meshes"])
    except (OSError, ValueError, KeyError):
        return False
    return np.allclose(got, sorted(times))


def _aggregate(reports: dict[str, dict[str, dict]], groups: dict[str, list[str]],
               methods: dict[str, list[str]], times: tuple[float, ...]) -> dict:
    """Mean scores per (group, method) and t over the group's trajectories."""
    out = {}
    for group, names in groups.items():
        out[group] = {}
        for method in methods[group]:
            per_t = []
            for t in sorted(times, reverse=True):
                entries = [next(e for e in reports[method][n]["per_t"] if abs(e["t"] - t) < 1e-9)
                           for n in names if n in reports.get(method, {})]
                ok = [e for e in entries if "error" not in e]
                row = {"t": t, "n": len(entries), "failed": len(entries) - len(ok)}
                for k in ("cd_x1e4", "emd_x1e2", "nce"):
                    row[k] = float(np.mean([e[k] for e in ok])) if ok else math.nan
                row["t_gt"] = [e["t_gt"] for e in entries]
                per_t.append(row)
            ok_rows = [r for r in per_t if r["n"] > r["failed"]]
            mean = {k: float(np.mean([r[k] for r in ok_rows])) if ok_rows else math.nan
                    for k in ("cd_x1e4", "emd_x1e2", "nce")}
            out[group][method] = {"trajectories": [n for n in names if n in reports.get(method, {})],
                                  "per_t": per_t, "mean": mean, "failed": sum(r["failed"] for r in per_t)}
    return out


def _montage(path: Path, traj_dir: Path, rows: dict[str, Path], times: tuple[float, ...], size: int,
             device: str | None) -> str:
    """Ground truth and each method's meshes (rows) at each t (columns), one camera for all frames."""
    from vnc_warp.render import Camera, montage, render_mesh, save_png

    from .data import read_trajectory
    from .metrics import read_prediction_dir

    traj = read_trajectory(traj_dir)
    order = sorted(times, reverse=True)
    gt_t = np.array([s.t for s in traj.stages])
    gt = [traj.load_stage(int(np.argmin(np.abs(gt_t - t)))) for t in order]
    camera = Camera.fit(gt[0], azimuth=30.0, elevation=20.0)
    frames, labels = [], []
    for m, t in zip(gt, order):
        frames.append(render_mesh(m, camera=camera, width=size, height=size, device=device))
        labels.append(f"GT {gt_t[int(np.argmin(np.abs(gt_t - t)))]:.2f}")
    blank = np.full((size, size, 3), 255, dtype=np.uint8)
    for label, folder in rows.items():
        preds, _ = read_prediction_dir(folder)
        for t in order:
            mesh = preds.get(t)
            frames.append(blank if mesh is None else render_mesh((mesh.vertices, mesh.faces), camera=camera,
                                                                 width=size, height=size, device=device))
            labels.append(f"{label} {t:.2f}")
    save_png(path, montage(frames, labels=labels, cols=len(order)))
    return str(path)


def _fig9b(path: Path, shape: _Shape, folder: Path, kind: str, config: ExperimentConfig, device: str | None) -> str:
    """Fig. 9b (:func:`vnc_warp.figures.decoded_trajectory`): the model's meshes across t above the VNC-Flow stages."""
    from vnc_warp.figures import decoded_trajectory
    from vnc_warp.mesh import load_mesh

    from .data import read_trajectory
    from .metrics import read_prediction_dir

    preds, _ = read_prediction_dir(folder)
    order = sorted(preds, reverse=True)
    traj = read_trajectory(shape.traj)
    role = "held-out" if shape.role == "holdout" else "distilled"
    decoded_trajectory([None if preds[t] is None else load_mesh(preds[t]) for t in order], order, path,
                       reference=[traj.load_stage(i) for i in range(len(traj.stages))],
                       reference_t=[s.t for s in traj.stages], frame_size=config.render_size,
                       title=f"Fig. 9b  {METHODS[kind]} on {role} {shape.name}", device=device)
    return str(path)


def run_experiment(config: ExperimentConfig, *, out_dir: str | os.PathLike, work_dir: str | os.PathLike,
                   meshes_dir: str | os.PathLike | None = None, device: str | None = None, progress: bool = True,
                   log: Callable[[str], None] = print) -> dict:
    """Run (or continue) the experiment; see the module docstring for the stages.

    Args:
        config: sizes and settings (:func:`preset`, :func:`load_experiment`).
        out_dir: folder of ``results.json``, ``results.md`` and the PNGs (small files only).
        work_dir: folder of everything else (trajectories, datasets, checkpoints, predictions);
            re-running with the same folder skips finished stages.
        meshes_dir: folder of the real mesh files (default: :func:`default_meshes_dir`).
        device: ``"cpu"``, ``"cuda:0"``...; None: CUDA when present (Warp and torch alike).
        progress: progress bars of flows and training.
        log: where one-line progress messages go.

    Returns:
        The content of ``results.json``.

    Raises:
        FileNotFoundError: a real mesh file is missing.
        ValueError: invalid config, a work folder made with other settings, or nothing left to train
            or evaluate after failed flows.
    """
    threads = torch.get_num_threads()
    if config.torch_threads is not None:
        torch.set_num_threads(config.torch_threads)
    try:
        return _run(config, Path(out_dir), Path(work_dir), meshes_dir, device, progress, log)
    finally:
        torch.set_num_threads(threads)


def _run(config: ExperimentConfig, out: Path, work: Path, meshes_dir: str | os.PathLike | None, device: str | None,
         progress: bool, log: Callable[[str], None]) -> dict:
    import vnc_warp._device  # noqa: F401  (quiet Warp first)
    import warp as wp

    from .baseline import latent_interpolation
    from .checkpoint import load_model
    from .data import TrajectoryDataset, build_dataset, read_trajectory
    from .inference import predict_times
    from .latent import latent_anatomy
    from .train import resolve_device

    config.validate()
    clock = _Clock(config.time_budget_s)
    out.mkdir(parents=True, exist_ok=True)
    _check_work_dir(work, config)
    meshes = Path(meshes_dir) if meshes_dir is not None else default_meshes_dir()
    torch_device = resolve_device(device)
    warp_device = device if device is not None else ("cuda:0" if torch_device.type == "cuda" else "cpu")
    results: dict[str, Any] = {"experiment": config.to_dict(), "notes": []}
    notes = results["notes"]

    with clock.stage("shapes", log):
        shapes = _shapes(config, work, meshes)
    with clock.stage("flows", log):
        _flows(shapes, config, warp_device, work, log)
    results["flows"] = {s.name: {"kind": s.kind, "role": s.role, **s.info} for s in shapes}
    ok = [s for s in shapes if s.status == "done"]
    failed = [s.name for s in shapes if s.status == "failed"]
    if failed:
        notes.append(f"flows failed (shapes left out): {failed}")
    cut = [s.name for s in shapes if s.status == "dropped"]
    if cut:
        notes.append(f"flow budget: {len(cut)} procedural training shape(s) left out: {cut}")
    train_shapes = [s for s in ok if s.role == "train"]
    holdout = [s for s in ok if s.role == "holdout"]
    if not train_shapes or not holdout:
        raise ValueError(f"after failed flows {failed}, {len(train_shapes)} training and {len(holdout)} held-out "
                         "trajectories are left; need at least one of each")
    distill = next((s for s in train_shapes if config.distill_mesh and s.name == Path(config.distill_mesh).stem), None)
    if config.distill_mesh and distill is None:
        notes.append(f"C-VAE-II skipped: the flow of {config.distill_mesh} failed")

    with clock.stage("dataset", log):
        ns, nu, nn_ = config.num_samples
        results["dataset"] = build_dataset([s.traj for s in train_shapes], work / "data", num_surface=ns,
                                           num_uniform=nu, num_near=nn_, truncation=config.truncation,
                                           device=warp_device, seed=config.seed, progress=progress)

    training, shares = {}, list(config.train_shares)
    runs = work / "runs"
    for kind in ("cvae1", "vae", "cvae2"):
        if kind == "cvae2" and distill is None:
            continue
        cfg = run_config(config, kind, pretrained=str((runs / "vae" / "checkpoints" / "last.pt").resolve()))
        with clock.stage(f"train_{kind}", log):
            data = TrajectoryDataset(work / "data", num_surface=cfg.data.num_surface, num_queries=cfg.data.num_queries,
                                     seed=cfg.seed, cache=True,
                                     # the "test" split is exactly the listed shapes: the distilled one
                                     split="test" if kind == "cvae2" else "all",
                                     holdout=(distill.name,) if kind == "cvae2" else (),
                                     repeats=config.distill_repeats if kind == "cvae2" else config.repeats)
            data.preload()
            training[kind] = _train(kind, cfg, data, runs / kind, device=str(torch_device),
                                    budget_s=_budget(clock, config, shares), config=config, progress=progress, log=log)
        shares.pop(0)

    models = {kind: load_model(runs / kind, device=torch_device) for kind in training}
    for kind, (model, _) in models.items():
        training[kind]["parameters"] = _param_count(model)
    results["training"] = training

    # Predictions: C-VAE-I and the baseline on every held-out trajectory and the distilled one; C-VAE-II on the latter.
    both = [*holdout, *([distill] if distill else [])]
    targets = {"cvae1": both, "baseline": both, "cvae2": [distill] if distill and "cvae2" in models else []}
    preds = work / "pred"
    with clock.stage("generate", log):
        for method, trajs in targets.items():
            for s in trajs:
                folder = preds / method / s.name
                if _predicted(folder, config.times):
                    continue
                if method == "baseline":
                    model, cfg = models["vae"]
                    latent_interpolation(model, s.traj, config.times, folder, resolution=config.resolution,
                                         num_surface=cfg.data.num_surface, seed=config.seed)
                else:
                    model, cfg = models[method]
                    predict_times(model, read_trajectory(s.traj).load_stage(0), config.times, folder,
                                  num_surface=cfg.data.num_surface, resolution=config.resolution, seed=config.seed,
                                  name=s.name, meta={"method": method})

    with clock.stage("evaluate", log):
        jobs, reports = [], {m: {} for m in targets}
        (work / "eval").mkdir(parents=True, exist_ok=True)
        for method, trajs in targets.items():
            for s in trajs:
                path = work / "eval" / f"{method}__{s.name}.json"
                if path.is_file():
                    reports[method][s.name] = json.loads(path.read_text())
                else:
                    jobs.append((method, s.name, {"pred": str(preds / method / s.name), "gt": str(s.traj),
                                                  "n_points": config.n_points, "n_emd": config.n_emd,
                                                  "seed": config.seed, "out": str(path)}))
        if config.eval_workers > 1 and len(jobs) > 1:
            ctx = multiprocessing.get_context("spawn")
            with cf.ProcessPoolExecutor(max_workers=min(config.eval_workers, len(jobs)), mp_context=ctx) as pool:
                futures = {pool.submit(_eval_job, job): (m, n) for m, n, job in jobs}
                for fut in cf.as_completed(futures):
                    m, n = futures[fut]
                    reports[m][n] = fut.result()
        else:
            for m, n, job in jobs:
                reports[m][n] = _eval_job(job)
        groups = {"held-out procedural": [s.name for s in holdout if s.kind == "procedural"],
                  "held-out real": [s.name for s in holdout if s.kind == "real"]}
        methods = {g: ["cvae1", "baseline"] for g in groups}
        if distill is not None:
            groups[f"distilled: {distill.name}"] = [distill.name]
            methods[f"distilled: {distill.name}"] = [m for m in ("cvae2", "cvae1", "baseline") if targets[m]]
        groups = {g: names for g, names in groups.items() if names}
        results["evaluation"] = {
            "groups": _aggregate(reports, groups, methods, config.times),
            "per_trajectory": {m: {n: {"per_t": r["per_t"], "mean": r["mean"], "failed": r["failed"]}
                                   for n, r in rs.items()} for m, rs in reports.items()},
            "sampling_floor": {n: r["sampling_floor"] for n, r in reports["cvae1"].items()},
            "conventions": next(iter(reports["cvae1"].values()))["conventions"],
        }

    with clock.stage("latent_anatomy", log):
        anatomy = {}
        model, cfg = models["cvae1"]
        kwargs = dict(title="C-VAE-I", num_surface=cfg.data.num_surface, seed=config.seed)
        try:
            anatomy["cvae1"] = latent_anatomy(model, [s.traj for s in holdout], **kwargs,
                                              figure=out / "fig11_latent_space.png" if config.figures else None)
        except Exception as exc:  # a figure must not cost the numbers
            notes.append(f"Fig. 11 not drawn: {type(exc).__name__}: {exc}")
            anatomy["cvae1"] = latent_anatomy(model, [s.traj for s in holdout], **kwargs)
        model, cfg = models["vae"]
        anatomy["vae"] = latent_anatomy(model, [s.traj for s in holdout], out_dir=None, title="VAE",
                                        num_surface=cfg.data.num_surface, seed=config.seed, use_umap=False)
        results["latent_anatomy"] = anatomy
        results["figures"] = list(anatomy["cvae1"]["plots"].values())

    results["environment"] = {"device": str(torch_device), "torch": torch.__version__, "warp": wp.__version__,
                              "python": platform.python_version(),
                              "gpu": torch.cuda.get_device_name(torch_device) if torch_device.type == "cuda" else None}
    notes.append("latent interp. (VAE): the plain VAE (same backbone as the C-VAEs) encodes the ground-truth stage 0 "
                 "and LAST stage and decodes their linear blend; it is given the final shape, the C-VAEs only stage 0")
    notes.append("each prediction is scored against the ground-truth stage nearest in t (t = 0 -> the last stage, "
                 "whose measured t is > 0)")
    if distill is not None:
        notes.append(f"{distill.name} is also a training shape of C-VAE-I and the VAE; C-VAE-II is trained on it alone")
    _write_results(out, results, clock)  # the numbers are safe before any figure is drawn

    if config.figures:
        with clock.stage("figures", log):
            shown = [s for s in holdout if s.kind == "real"][:1] or holdout[:1]
            for s, model_kind in [*((h, "cvae1") for h in shown), *([(distill, "cvae2")] if distill else [])]:
                rows = {_SHORT[m]: preds / m / s.name for m in (model_kind, "baseline")}
                try:
                    results["figures"].append(_fig9b(out / f"fig9b_{model_kind}_{s.name}.png", s,
                                                     preds / model_kind / s.name, model_kind, config, warp_device))
                    results["figures"].append(_montage(out / f"compare_{s.name}.png", s.traj, rows, config.times,
                                                       config.render_size, warp_device))
                except Exception as exc:  # a figure must not cost the numbers
                    notes.append(f"figure of {s.name} not drawn: {type(exc).__name__}: {exc}")
        _write_results(out, results, clock)
    log(f"[experiment] done in {clock.total():.1f} s: {out / 'results.json'}, {out / 'results.md'}")
    return results


def _write_results(out: Path, results: dict, clock: _Clock) -> None:
    results["timings_s"] = {**clock.seconds, "total": clock.total()}
    for name, text in (("results.json", json.dumps(_finite(results), indent=1)),
                       ("results.md", results_markdown(results))):
        tmp = out / f"{name}.tmp"
        tmp.write_text(text)
        os.replace(tmp, out / name)


def _finite(obj: Any) -> Any:
    """NaN / inf -> None, so that results.json is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def _fmt(x: Any, digits: int = 3) -> str:
    return "n/a" if x is None or (isinstance(x, float) and not math.isfinite(x)) else f"{x:.{digits}f}"


def results_markdown(results: dict) -> str:
    """The tables of a ``results.json`` as Markdown."""
    exp = results["experiment"]
    lines = [f"# C-VAE experiment `{exp['name']}`", ""]
    groups = results["evaluation"]["groups"]
    times = sorted(exp["times"], reverse=True)
    for key, title in (("cd_x1e4", "CD x1e-4"), ("emd_x1e2", "EMD x1e-2"), ("nce", "NCE (rad)")):
        lines += [f"## {title} (lower is better)", "",
                  "| trajectories | method | " + " | ".join(f"t={t:g}" for t in times) + " | mean | failed |",
                  "|---|---|" + "---|" * (len(times) + 2)]
        for group, rows in groups.items():
            for method, row in rows.items():
                by_t = {r["t"]: r for r in row["per_t"]}
                cells = [_fmt(by_t[t][key]) if t in by_t else "n/a" for t in times]
                lines.append(f"| {group} ({len(row['trajectories'])}) | {METHODS[method]} | " + " | ".join(cells)
                             + f" | {_fmt(row['mean'][key])} | {row['failed']} |")
        lines.append("")
    floors = list(results["evaluation"]["sampling_floor"].values())
    if floors:
        lines += ["Sampling floor (GT stage 0 against itself resampled), mean over the evaluated trajectories: "
                  + ", ".join(f"{k} {_fmt(float(np.mean([f[k] for f in floors if f[k] is not None])))}"
                              for k in ("cd_x1e4", "emd_x1e2", "nce")), ""]
    lines += ["## Training", "", "| model | parameters (trainable) | items | steps | batch | seconds | samples/s "
              "(end to end) | samples/s (steady) | final loss | final L_tsdf |", "|---" * 10 + "|"]
    for kind, tr in results["training"].items():
        p = tr.get("parameters", {})
        lines.append(f"| {MODELS[kind]} | {p.get('total', 0):,} ({p.get('trainable', 0):,}) | {tr['items']} | "
                     f"{tr['steps']} | {tr['batch_size']} | {_fmt(tr['seconds'], 1)} | "
                     f"{_fmt(tr['samples_per_s'], 1)} | "
                     f"{_fmt(tr['steady_samples_per_s'], 1)} | {_fmt(tr['final'].get('loss'), 4)} | "
                     f"{_fmt(tr['final'].get('tsdf'), 4)} |")
    lines += ["", "## Latent anatomy (held-out trajectories, every stage)", "",
              "| model | encoding | samples | r(norm, t) | r(norm, t) within trajectory | abs r(PC1, t) | "
              "r(PC1, t) within trajectory | PC1, PC2 variance |", "|---|---|---|---|---|---|---|---|"]
    for kind, rep in results["latent_anatomy"].items():
        ev = ", ".join(_fmt(v, 2) for v in rep["explained_variance_ratio"])
        lines.append(f"| {MODELS[kind]} | {rep['encoding']} | {rep['n']} | {_fmt(rep['norm_t_pearson'])} | "
                     f"{_fmt(rep.get('norm_t_pearson_within'))} | {_fmt(rep['pc1_t_abs_pearson'])} | "
                     f"{_fmt(rep.get('pc1_t_pearson_within'))} | {ev} |")
    t = results["timings_s"]
    lines += ["", "## Wall time (s)", "", "| " + " | ".join(t) + " |", "|" + "---|" * len(t),
              "| " + " | ".join(_fmt(v, 1) for v in t.values()) + " |", ""]
    flows = results["flows"]
    done = [f for f in flows.values() if f.get("status") in ("done", "skipped (done)")]
    lines += [f"Flows: {len(done)} of {len(flows)} trajectories, {exp['stages']} stages each; "
              f"environment: {results['environment']}", ""]
    lines += ["## Notes", ""] + [f"- {n}" for n in results["notes"]] + [""]
    return "\n".join(lines)
