"""The C-VAE experiment of Sec. 4.3 end to end, from procedural shapes to one results table.

:func:`run_experiment` runs, in order, each stage skipped when its output is already there (an
interrupted run continues where it stopped):

1. **shapes**: procedural genus-0 blobs (:func:`vnc_warp.shapes.random_shape`) and humanoid bodies
   (:func:`vnc_warp.shapes.humanoid`), made inside the flow jobs, and the real meshes named by the config,
   read from a folder (nothing is downloaded);
2. **flows**: one VNC-Flow trajectory per shape (Algorithm 1, :func:`vnc_warp.flow` with ``out_dir``,
   resumable), in a pool of processes when ``flow_workers > 1``; the distilled body gets ``distill_stages``;
3. **dataset**: truncated-SDF samples of the training trajectories and the distilled one
   (:func:`~vnc_warp.training.data.build_dataset`);
4. **training**: C-VAE-I on the procedural and real training shapes; the plain VecSet VAE of the same size
   on the same shapes (every stage auto-encoded) for the same wall-clock budget; C-VAE-II on the distilled
   trajectory on top of the frozen VAE encoder. With a budget the step count comes from a measured
   throughput (a short calibration run);
5. **generation**: meshes at the measured t of the ground-truth stage nearest each of ``times`` (``resolution``^3
   marching cubes) from the held-out shapes' stage 0
   (C-VAE-I), from the distilled shape (C-VAE-II, C-VAE-I) and from the latent-interpolation baseline
   (:mod:`vnc_warp.training.baseline`) on the same trajectories;
6. **evaluation**: CD / EMD / NCE (Tab. 2, :func:`~vnc_warp.training.metrics.evaluate_trajectory`) of every
   prediction against the ground-truth stage nearest in t, whole and largest component, package frame and
   unit box, beside the sampling floor of each scored stage at the same counts;
7. **latent anatomy** (Fig. 11): C-VAE-I latents of every stage of the held-out trajectories: norm vs t and
   the principal direction that best orders each trajectory by t (:func:`~vnc_warp.training.latent.latent_anatomy`);
   the plain VAE's latents of the same stages as a control;
8. **results**: ``results.json``, ``results.md`` (tables and the issue's checks) and at most six PNGs in
   ``out_dir``; trajectories, datasets, checkpoints and predicted meshes stay in ``work_dir``.

The stages are grouped into :data:`STEPS` (data, train, generate, report) so that a run can be made of
separate commands of bounded length (``vnc-warp experiment --step N``): step N runs (or skips, when done)
every stage up to its last one. Sizes come from an :class:`ExperimentConfig`; :data:`PRESETS` holds
``cpu-smoke`` (minutes on a 2-core CPU), ``cpu-rehearsal`` (the ``gpu`` pipeline at CPU sizes) and ``gpu``
(one H100/H200, five calls of at most about 9 minutes). A call with ``max_minutes`` stops training (with a
checkpoint) and generation at that time and returns ``unfinished``; the same call again goes on where it stopped,
the models trained as in one call.
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
import shutil
import time
import typing
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import torch

from .config import DataConfig, LossConfig, ModelConfig, OptimConfig, TrainConfig, _from_dict

__all__ = ["ExperimentConfig", "PRESETS", "STEPS", "preset", "load_experiment", "run_experiment",
           "default_meshes_dir", "results_markdown", "check_results"]

METHODS = {"cvae1": "C-VAE-I", "cvae2": "C-VAE-II", "baseline": "latent interp. (VAE)"}
_SHORT = {"cvae1": "C-VAE-I", "cvae2": "C-VAE-II", "baseline": "interp."}
MODELS = {"cvae1": "C-VAE-I", "vae": "VAE (baseline; C-VAE-II's frozen encoder)", "cvae2": "C-VAE-II"}
STEPS = {1: "data", 2: "train", 3: "generate", 4: "report"}
# settings that change how fast a run goes, not what it computes: a work folder may be resumed with others
_RUNTIME_KEYS = ("name", "flow_workers", "flow_budget_s", "eval_workers", "torch_threads", "figures",
                 "train_budget_s", "distill_budget_s", "render_size", "data_workers", "max_minutes")
#: A call with a time limit starts training a second model only with this many seconds left (or a quarter of the
#: limit, when less): the first model of a call always starts, so that every call gets on.
_MIN_START_S = 60.0
#: Exit status of ``vnc-warp experiment`` when the time limit ended the call before its step was done.
UNFINISHED_EXIT = 3


@dataclass
class ExperimentConfig:
    """Everything :func:`run_experiment` needs besides the folders and the device.

    Attributes:
        name: label (the preset's name).
        num_shapes: procedural genus-0 blobs (:func:`vnc_warp.shapes.random_shape`).
        shape_seed: seed of the blob and humanoid families.
        subdivisions: icosphere subdivisions of the blobs (3: 642 vertices, 4: 2562).
        holdout_shapes: the last this many blobs are held out (never trained on).
        num_humanoids: procedural bodies (:func:`vnc_warp.shapes.humanoid`).
        holdout_humanoids: the last this many bodies are held out.
        humanoid_voxel: marching-cubes voxel of the bodies (metres; the flow remeshes them to ``real_faces``).
        train_meshes: real mesh files (in the meshes folder) added to the training set.
        holdout_meshes: real mesh files held out (generalization, latent anatomy).
        distill_mesh: the real mesh C-VAE-II distils (Sec. 4.3), one of ``train_meshes`` or ``holdout_meshes``
            (held out, C-VAE-I and the VAE never see it); ``""`` skips C-VAE-II.
        distill_stages: VNC-Flow stages of the distilled trajectory (0: ``stages``).
        real_faces: face count of the remeshed states of real meshes and humanoids (their flows' ``faces``).
        real_resolution: SDF-remesh grid nodes for the real meshes (None: automatic).
        stages: VNC-Flow stages N.
        max_iters: VNC-Flow iteration cap per stage.
        substage_budget: VNC-Flow's largest share of ``S_init`` between two remeshes (None: the flow's default,
            1/32; ``1/stages`` flows each stage in one piece).
        flow_workers: processes making shapes and running flows at once (1: in this process).
        flow_budget_s: seconds after which procedural training shapes whose flow has not started are
            left out (held-out and real shapes always flow, first); None: no limit.
        num_samples: surface points, uniform and near-surface queries per stage of the dataset (the pools
            every item draws a fresh subset from).
        num_reference: queries per stage near the trajectory's stage 0, labelled with the stage's SDF (where
            remnants of the detailed input float; see :func:`~vnc_warp.training.data.build_dataset`).
        grid_resolution: nodes per axis of each stage's stored TSDF grid, from which items label fresh far
            queries (``data.fresh_fraction``); 0: none.
        noise: standard deviations of the near-surface queries (normalized units), split evenly.
        truncation: TSDF truncation (normalized units).
        backbone: the VecSet backbone shared by all three models (``kind`` and ``pretrained`` are set
            per model): the baseline VAE is the C-VAE's size by construction.
        cvae1, vae, cvae2: training configurations; their ``model`` sections are replaced by
            ``backbone`` and their ``data.encoder_input`` by the model's (the item itself for the VAE, stage 0
            for C-VAE-II, stage 0 or a trajectory suffix's start for C-VAE-I). ``optim.total_steps`` is the step count, or the cap with a budget.
        repeats: passes over the training stages per data-loader epoch.
        distill_repeats: the same for the single distilled trajectory.
        train_budget_s: wall-clock seconds of training C-VAE-I and, the same, of the VAE, in all (over every call);
            None trains the configured steps.
        cvae1_fork: None trains C-VAE-I from scratch; a fraction f in (0, 1) starts it from the VAE's weights at
            f of the VAE's planned steps (the time branch from the identity) and gives it (1 - f) of the
            VAE's budget (``train_budget_s``, or the steps), so that both models get the same optimisation in
            all. The VAE then trains first.
        distill_budget_s: wall-clock seconds of training C-VAE-II, in all; None trains the configured steps.
        max_minutes: wall-clock minutes of one call of :func:`run_experiment`, counted from its start: training
            stops with a checkpoint at the end of the first step past it, generation before the next prediction,
            and the call returns with ``unfinished`` set; the same call again resumes (the run is the one trained
            in one go), scoring before its next job (the running ones end and are kept). None: no limit. Flows and
            the dataset are not cut.
        calibration_steps: steps timed before the step count of a budgeted model is fixed.
        min_steps: fewest steps of a budgeted model.
        data_workers: DataLoader workers of every model (None: each section's ``data.num_workers``).
        torch_threads: torch CPU threads while training (None: torch's default).
        times: normalized times the models are decoded at.
        resolution: marching-cubes grid samples per axis.
        n_points, n_emd: surface samples for CD/NCE and for the exact EMD.
        eval_workers: processes scoring predictions at once.
        figures: write the figures.
        render_size: pixels per montage frame.
        seed: seed of the evaluation and anatomy sampling.
    """

    name: str = "custom"
    num_shapes: int = 6
    shape_seed: int = 0
    subdivisions: int = 3
    holdout_shapes: int = 1
    num_humanoids: int = 0
    holdout_humanoids: int = 0
    humanoid_voxel: float = 0.012
    train_meshes: tuple[str, ...] = ("spot_lowres.obj", "human_man.obj")
    holdout_meshes: tuple[str, ...] = ("fandisk.obj",)
    distill_mesh: str = "human_man.obj"
    distill_stages: int = 0
    real_faces: int = 1280
    real_resolution: int | None = 40
    stages: int = 3
    max_iters: int = 300
    substage_budget: float | None = None
    flow_workers: int = 1
    flow_budget_s: float | None = None
    num_samples: tuple[int, int, int] = (2048, 2048, 2048)
    num_reference: int = 0
    grid_resolution: int = 0
    noise: tuple[float, ...] = (0.005, 0.02)
    truncation: float = 0.1
    backbone: ModelConfig = field(default_factory=ModelConfig)
    cvae1: TrainConfig = field(default_factory=TrainConfig)
    vae: TrainConfig = field(default_factory=TrainConfig)
    cvae2: TrainConfig = field(default_factory=TrainConfig)
    repeats: int = 1
    distill_repeats: int = 4
    train_budget_s: float | None = None
    cvae1_fork: float | None = None
    distill_budget_s: float | None = None
    max_minutes: float | None = None
    calibration_steps: int = 30
    min_steps: int = 100
    data_workers: int | None = None
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
        if self.num_shapes < 0 or not 0 <= self.holdout_shapes <= self.num_shapes:
            raise ValueError(f"need num_shapes >= 0 and 0 <= holdout_shapes <= num_shapes, got {self.num_shapes} "
                             f"and {self.holdout_shapes}")
        if self.num_humanoids < 0 or not 0 <= self.holdout_humanoids <= self.num_humanoids:
            raise ValueError(f"need num_humanoids >= 0 and 0 <= holdout_humanoids <= num_humanoids, got "
                             f"{self.num_humanoids} and {self.holdout_humanoids}")
        if not self.humanoid_voxel > 0:
            raise ValueError(f"humanoid_voxel must be positive, got {self.humanoid_voxel}")
        if not (self.holdout_shapes or self.holdout_humanoids or self.holdout_meshes):
            raise ValueError("nothing is held out: set holdout_shapes or holdout_humanoids > 0, or list holdout_meshes")
        if (self.num_shapes - self.holdout_shapes + self.num_humanoids - self.holdout_humanoids
                + len(self.train_meshes)) < 1:
            raise ValueError("nothing to train on: no procedural training shape and no train_meshes")
        if self.distill_mesh and self.distill_mesh not in (*self.train_meshes, *self.holdout_meshes):
            raise ValueError(f"distill_mesh {self.distill_mesh!r} must be one of train_meshes "
                             f"{list(self.train_meshes)} or holdout_meshes {list(self.holdout_meshes)}")
        names = [Path(m).stem for m in (*self.train_meshes, *self.holdout_meshes)]
        if len(set(names)) != len(names):
            raise ValueError(f"real mesh names must be unique (train and held out together), got {names}")
        if min(self.stages, self.max_iters, self.flow_workers, self.eval_workers) < 1 or self.distill_stages < 0:
            raise ValueError("stages, max_iters, flow_workers and eval_workers must be >= 1, distill_stages >= 0")
        if self.substage_budget is not None and not 0.0 < self.substage_budget <= 1.0:
            raise ValueError(f"substage_budget must be in (0, 1] or None, got {self.substage_budget}")
        if min(self.num_samples) < 1 or self.repeats < 1 or self.distill_repeats < 1 or self.num_reference < 0:
            raise ValueError("num_samples, repeats and distill_repeats must be >= 1, num_reference >= 0")
        if not self.noise or min(self.noise) <= 0:
            raise ValueError(f"noise must list positive standard deviations, got {list(self.noise)}")
        if not self.times or not all(0.0 <= t <= 1.0 for t in self.times):
            raise ValueError(f"times must be a non-empty list in [0, 1], got {list(self.times)}")
        if self.cvae1_fork is not None and not 0.0 < self.cvae1_fork < 1.0:
            raise ValueError(f"cvae1_fork must be in (0, 1) or None, got {self.cvae1_fork}")
        for key in ("flow_budget_s", "train_budget_s", "distill_budget_s", "max_minutes"):
            value = getattr(self, key)
            if value is not None and not value > 0:
                raise ValueError(f"{key} must be positive or None, got {value}")
        if not 1 <= self.n_emd <= self.n_points or self.resolution < 8:
            raise ValueError("need 1 <= n_emd <= n_points and resolution >= 8")
        if self.data_workers is not None and self.data_workers < 0:
            raise ValueError(f"data_workers must be >= 0 or None, got {self.data_workers}")
        for kind in ("cvae1", "vae", "cvae2"):
            run_config(self, kind, pretrained="vae.pt").validate()


def run_config(config: ExperimentConfig, kind: str, *, pretrained: str | None = None) -> TrainConfig:
    """The training configuration of model ``kind`` (``cvae1``, ``vae``, ``cvae2``): its section of
    ``config`` with the shared backbone and the model's encoder input; ``pretrained`` is the VAE checkpoint
    C-VAE-II (and C-VAE-I with ``cvae1_fork``) starts from."""
    section = getattr(config, kind)
    cfg = TrainConfig.from_dict(section.to_dict())
    starts_from_vae = kind == "cvae2" or (kind == "cvae1" and config.cvae1_fork is not None)
    cfg.model = dataclasses.replace(config.backbone, kind=kind, pretrained=pretrained if starts_from_vae else None)
    if kind == "vae":
        encoder_input = "item"
    elif kind == "cvae2":
        encoder_input = "stage0"
    else:
        encoder_input = "suffix" if section.data.encoder_input == "suffix" else "stage0"
    cfg.data = dataclasses.replace(cfg.data, encoder_input=encoder_input)
    cfg.name = f"{config.name}-{kind}"
    return cfg


def _train_section(*, lr: float, steps: int, warmup: int, batch: int, surface: int, queries: int, workers: int,
                   kl: float, linear_kl: bool, eik_queries: int, log_every: int, ckpt_every: int,
                   kl_time_ratio: float = 1.0, near_fraction: float = 0.5, on_surface: int = 0,
                   surface_weight: float = 0.0, normal_weight: float = 0.0, fresh_fraction: float = 0.0,
                   encoder_input: str = "stage0", detail_share: float = 0.0, symmetry: bool = False) -> TrainConfig:
    loss = LossConfig(kl_weight=kl, kl_schedule="linear" if linear_kl else "constant", kl_weight_start=0.0,
                      kl_warmup_start=steps // 10 if linear_kl else 0, kl_warmup_steps=steps // 2 if linear_kl else 0,
                      kl_time_ratio=kl_time_ratio, eikonal_weight=0.01, eikonal_queries=eik_queries,
                      surface_weight=surface_weight, normal_weight=normal_weight)
    return TrainConfig(loss=loss, optim=OptimConfig(lr=lr, weight_decay=0.01, warmup_steps=warmup, total_steps=steps,
                                                    min_lr_ratio=0.1),
                       data=DataConfig(num_surface=surface, num_queries=queries, batch_size=batch, num_workers=workers,
                                       near_fraction=near_fraction, num_on_surface=on_surface,
                                       fresh_fraction=fresh_fraction, encoder_input=encoder_input,
                                       detail_share=detail_share, symmetry=symmetry),
                       bf16=True, log_every=log_every, ckpt_every=ckpt_every)


# The recipe of every model (issue 24): half the queries near the surface, half of the others drawn afresh for
# every item (labelled from the stage's TSDF grid), the surface and normal terms, the narrow posterior at init
# (ModelConfig.logvar_init), a decoder that starts from empty space (ModelConfig.sdf_init = the truncation);
# C-VAE-I's KL prior contracts toward t = 0 (the radial structure). C-VAE-I encodes every stage as the start of
# its trajectory's suffix (SuffixInput: ~N+1 times the encoder inputs of stage 0 alone, against which it memorised
# its ~70 training shapes and decoded blobs for unseen ones). The box symmetries (data.symmetry) stay off: on one
# H200 at f2eadcb they left C-VAE-I's held-out CD at t = 1 as it was (733 -> 738) and made the VAE's 7x worse
# (136 -> 1001) within the 180 s budget (docs/results/cvae24_h200_f2eadcb), a handicapped baseline.
_RECIPE = dict(near_fraction=0.5, fresh_fraction=0.5, surface_weight=1.0, normal_weight=0.05)
# C-VAE-I's items are its shape's stage 0 at t = 1 with this probability (SuffixInput's detail_share): with 8-stage
# trajectories the stage-0 items are then 1/9 + 8/9 * 0.2 = 29 % of the draws instead of 11 %. In the sixth H200 run
# (4ab2101) C-VAE-I lost to latent interpolation at t = 1 on the held-out real bodies only (human_man 22 vs 13, FAUST
# 71 vs 63), where it won from t = 0.75 to 0.25 by 1.3-12x: t = 1 (the detailed input auto-encoded) is the part of
# its task it saw least. This was chosen from that held-out result; see the README's seventh run.
_DETAIL_SHARE = 0.2


def _sections(*, lr: float, steps: int, warmup: int, common: dict, distill: dict | None = None) -> dict:
    """The three models' training sections: beta_kl 1e-3 warmed up for C-VAE-I (with the temporal prior, ratio
    100) and the VAE alike, 1e-4 for C-VAE-II; suffix inputs for C-VAE-I; ``distill`` overrides ``common`` for
    C-VAE-II."""
    kw = dict(lr=lr, steps=steps, warmup=warmup)
    return {"cvae1": _train_section(**kw, kl=1e-3, linear_kl=True, kl_time_ratio=100.0, encoder_input="suffix",
                                    detail_share=_DETAIL_SHARE, **common),
            "vae": _train_section(**kw, kl=1e-3, linear_kl=True, **common),
            "cvae2": _train_section(**kw, kl=1e-4, linear_kl=False, **(distill or common))}


def _tiny_backbone() -> ModelConfig:
    """~0.3M-parameter models for CPU runs."""
    return ModelConfig(width=64, heads=4, num_latents=32, latent_dim=8, encoder_depth=1, decoder_depth=2, num_freqs=6,
                       chunk_size=16384, time_tokens=2, time_freq_dim=64, modulator_depth=1, sdf_init=0.1)


# SDF-remesh grid of the real meshes in the CPU presets: at 40 nodes the first remesh of human_man.obj at 1280 faces
# refused (its fingers, thinner than the 0.047 spacing, broke off: 2.0 % of the area farther than 2 edge lengths), so
# cpu-smoke skipped C-VAE-II; at 64 it flows in 9.6 s on one CPU thread (automatic: 43 s)
_SMALL_GRID = 64


def _cpu_smoke() -> ExperimentConfig:
    """About 2 minutes on a 2-core CPU: 6 shapes of 642 vertices (one held out), Spot and the SMPL body
    remeshed to 1280 faces for training, fandisk held out, 3 stages flowed in one piece each (no sub-stages),
    ~0.3M-parameter models, fixed steps."""
    small = dict(batch=4, surface=256, queries=256, workers=0, eik_queries=64, log_every=10, ckpt_every=100,
                 on_surface=64, **_RECIPE)
    return ExperimentConfig(
        name="cpu-smoke", num_shapes=6, shape_seed=0, subdivisions=3, holdout_shapes=1,
        train_meshes=("spot_lowres.obj", "human_man.obj"), holdout_meshes=("fandisk.obj",),
        distill_mesh="human_man.obj",
        real_faces=1280, real_resolution=_SMALL_GRID, stages=3, max_iters=200, substage_budget=1 / 3, flow_workers=1,
        num_samples=(2048, 2048, 2048),
        num_reference=1024, grid_resolution=32, backbone=_tiny_backbone(),
        **_sections(lr=1e-3, steps=500, warmup=20, common=small),
        repeats=1, distill_repeats=4, torch_threads=1, resolution=48, n_points=5000, n_emd=500,
        eval_workers=1, figures=True, render_size=128)


# Real meshes of ../shared/data/meshes the gpu preset trains on: every closed genus-0 one except the bodies
# (held out), the duplicate Spot (spot_lowres is the same cow) and sword.obj. Sword's blade is thinner than the
# 6,000-face grid: its first remesh was refused in the fifth to eighth GPU runs, and since it gets a finer grid its flow
# is slow (stage 1 of 8 took 677 s on the CPU), while flows are not cut by max_minutes. The ninth run left it out.
_REAL_TRAIN = ("spot_lowres.obj", "bunny.obj", "armadillo.obj", "fandisk.obj", "goathead.obj", "penguin.obj",
               "wingnut.obj", "brucewick.obj", "springer.obj", "fish.obj", "mushroom.obj", "hammer.obj",
               "koala.obj", "nefertiti.obj", "scorpion.obj")
_BODIES = ("human_man.obj", "faust_tr_reg_025.ply")


def _gpu() -> ExperimentConfig:
    """One H100 or H200, about 25 minutes in five calls of at most ~9 minutes (steps 1, 2, 2, 3, 4: step 2 trains
    the VAE for 380 s and C-VAE-I from the VAE's half-way weights for 190 s, and is cut by ``max_minutes`` = 8.5
    into two calls).

    60 humanoids (5 held out), 16 blobs (1 held out) and 16 real meshes for training, the two real bodies held
    out; every shape flowed by VNC-Flow to 8 stages at 6,000 faces, the distilled body (human_man) to 32.
    Models 384 wide, 512 x 32 latents, 2 + 6 layers (~20M parameters), bf16; C-VAE-I and the VAE 380 s of
    training each in all, the first 190 s shared (``cvae1_fork`` = 0.5: from scratch in 300 s C-VAE-I underfit,
    its t = 1 bodies in pieces, in the fifth H200 run), C-VAE-II 300 s (330 s gave 1.3-1.9x the floor); 256^3
    marching cubes, CD on 100k points, EMD on 4,096.
    """
    big = dict(batch=32, surface=4096, queries=8192, workers=8, eik_queries=512, log_every=20, ckpt_every=200,
               on_surface=1024, **_RECIPE)
    distill = dict(big, batch=16, queries=16384, on_surface=2048)
    return ExperimentConfig(
        name="gpu", num_shapes=16, shape_seed=0, subdivisions=4, holdout_shapes=1, num_humanoids=60,
        holdout_humanoids=5, humanoid_voxel=0.01, train_meshes=_REAL_TRAIN, holdout_meshes=_BODIES,
        distill_mesh="human_man.obj", distill_stages=32,
        real_faces=6000, real_resolution=None, stages=8, max_iters=300, flow_workers=12, flow_budget_s=330.0,
        num_samples=(32768, 16384, 65536), num_reference=16384, grid_resolution=80, noise=(0.003, 0.01, 0.03),
        backbone=ModelConfig(width=384, heads=6, num_latents=512, latent_dim=32, encoder_depth=2, decoder_depth=6,
                             num_freqs=8, chunk_size=65536, time_tokens=4, time_freq_dim=256, modulator_depth=2,
                             sdf_init=0.1),
        **_sections(lr=4e-4, steps=20000, warmup=100, common=big, distill=distill),
        repeats=8, distill_repeats=64, train_budget_s=380.0, cvae1_fork=0.5, distill_budget_s=300.0, max_minutes=8.5,
        calibration_steps=30,
        min_steps=100, torch_threads=None, resolution=256, n_points=100_000, n_emd=4096, eval_workers=14,
        figures=True, render_size=192)


def _cpu_rehearsal() -> ExperimentConfig:
    """The ``gpu`` preset's pipeline at CPU sizes: every kind of shape, the held-out bodies, the 4 steps, the
    same evaluation protocol at small counts (tens of minutes on a 2-core CPU)."""
    cfg = _gpu()
    small = dict(batch=4, surface=256, queries=512, workers=0, eik_queries=64, log_every=10, ckpt_every=40,
                 on_surface=64, **_RECIPE)
    return dataclasses.replace(
        cfg, name="cpu-rehearsal", num_shapes=2, holdout_shapes=1, subdivisions=3, num_humanoids=3,
        holdout_humanoids=1, humanoid_voxel=0.02, train_meshes=("spot_lowres.obj", "goathead.obj"),
        distill_stages=4, real_faces=1000, real_resolution=_SMALL_GRID, stages=2, max_iters=60, flow_workers=2,
        flow_budget_s=None, num_samples=(2048, 1024, 3072), num_reference=1024, grid_resolution=32,
        backbone=_tiny_backbone(), **_sections(lr=1e-3, steps=400, warmup=20, common=small),
        repeats=2, distill_repeats=4, train_budget_s=40.0, distill_budget_s=30.0, max_minutes=None,
        calibration_steps=10, min_steps=20, torch_threads=1, resolution=48, n_points=4000, n_emd=256, eval_workers=2, render_size=96)


PRESETS: dict[str, Callable[[], ExperimentConfig]] = {"cpu-smoke": _cpu_smoke, "cpu-rehearsal": _cpu_rehearsal,
                                                      "gpu": _gpu}


def preset(name: str) -> ExperimentConfig:
    """A fresh copy of a named experiment (``cpu-smoke``, ``cpu-rehearsal`` or ``gpu``).

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
    """Wall time per stage, in this call and summed over every call on the work folder (``timings.json``)."""

    def __init__(self, path: Path | None = None) -> None:
        self.start = time.perf_counter()
        self.path = path
        self.seconds: dict[str, float] = {}

    @contextlib.contextmanager
    def stage(self, name: str, log: Callable[[str], None]) -> Iterator[None]:
        log(f"[experiment] {name} ...")
        t0 = time.perf_counter()
        try:
            yield
        finally:
            spent = time.perf_counter() - t0
            self.seconds[name] = self.seconds.get(name, 0.0) + spent
            if self.path is not None:
                totals = json.loads(self.path.read_text()) if self.path.is_file() else {}
                totals[name] = totals.get(name, 0.0) + spent
                self.path.write_text(json.dumps(totals, indent=1))
            log(f"[experiment] {name}: {self.seconds[name]:.1f} s")

    def totals(self) -> dict[str, float]:
        """Seconds per stage over every call (this one included), and their sum."""
        totals = json.loads(self.path.read_text()) if self.path is not None and self.path.is_file() else self.seconds
        return {**totals, "total": float(sum(totals.values()))}

    def total(self) -> float:
        return time.perf_counter() - self.start


@dataclass
class _Shape:
    name: str
    source: Path
    kind: str  # "blob" | "humanoid" | "real"
    role: str  # "train" | "holdout"
    faces: int | None
    resolution: int | None
    stages: int
    traj: Path
    recipe: dict | None = None  # how to make a procedural source (None: a real mesh file)
    status: str = "pending"
    info: dict = field(default_factory=dict)

    @property
    def procedural(self) -> bool:
        return self.kind != "real"


def _check_work_dir(work: Path, config: ExperimentConfig) -> None:
    """A work folder belongs to one experiment: refuse one made with other sizes (stale outputs)."""
    stamp = work / "experiment.json"
    key = {k: v for k, v in config.to_dict().items() if k not in _RUNTIME_KEYS}
    if stamp.is_file():
        old = json.loads(stamp.read_text())
        # a setting added since the stamp was written reads as None (its default) there
        diff = sorted(k for k in set(old) | set(key) if old.get(k) != key.get(k))
        if diff:
            raise ValueError(f"{work} holds an experiment with other settings ({', '.join(diff)} differ); "
                             "use another --work folder")
        return
    work.mkdir(parents=True, exist_ok=True)
    stamp.write_text(json.dumps(key, indent=1))


def _shapes(config: ExperimentConfig, work: Path, meshes_dir: Path | None) -> list[_Shape]:
    """Every shape of the experiment with its role; procedural sources are made later, in the flow jobs."""
    from vnc_warp.shapes import family_seeds

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
    blob_seeds = family_seeds(config.num_shapes, config.shape_seed) if config.num_shapes else []
    for i, seed in enumerate(blob_seeds):
        name = f"family{config.shape_seed}_{i:04d}"
        role = "holdout" if i >= config.num_shapes - config.holdout_shapes else "train"
        shapes.append(_Shape(name, folder / f"{name}.ply", "blob", role, None, None, config.stages, work / "traj" / name,
                             recipe={"kind": "blob", "seed": seed, "subdivisions": config.subdivisions}))
    body_seeds = family_seeds(config.num_humanoids, config.shape_seed) if config.num_humanoids else []
    for i, seed in enumerate(body_seeds):
        name = f"human{config.shape_seed}_{i:04d}"
        role = "holdout" if i >= config.num_humanoids - config.holdout_humanoids else "train"
        shapes.append(_Shape(name, folder / f"{name}.ply", "humanoid", role, config.real_faces, None, config.stages,
                             work / "traj" / name, recipe={"kind": "humanoid", "seed": seed,
                                                           "voxel": config.humanoid_voxel}))
    for files, role in ((config.train_meshes, "train"), (config.holdout_meshes, "holdout")):
        for file in files:
            name = Path(file).stem
            stages = config.distill_stages or config.stages if file == config.distill_mesh else config.stages
            shapes.append(_Shape(name, (meshes_dir / file).resolve(), "real", role, config.real_faces,
                                 config.real_resolution, stages, work / "traj" / name))
    return shapes


def _make_source(path: Path, recipe: dict) -> None:
    """Write a procedural shape (atomically; an existing file is kept)."""
    if path.is_file():
        return
    from vnc_warp.shapes import humanoid, random_shape

    if recipe["kind"] == "blob":
        mesh = random_shape(recipe["seed"], subdivisions=recipe["subdivisions"], name=path.stem)
    else:
        mesh = humanoid(recipe["seed"], voxel=recipe["voxel"], name=path.stem)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.ply")
    mesh.save(tmp)
    os.replace(tmp, path)


def _flow_job(job: dict) -> dict:
    """Make the shape (procedural) and run (or resume) its VNC-Flow; module-level so that a process pool can
    pickle it. Flows through the package's public :func:`vnc_warp.flow`."""
    import vnc_warp
    import vnc_warp._device  # noqa: F401  (quiet Warp first)

    t0 = time.perf_counter()
    try:
        if job["recipe"] is not None:
            _make_source(Path(job["source"]), job["recipe"])
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            traj = vnc_warp.flow(job["source"], stages=job["stages"], faces=job["faces"], device=job["device"],
                                 out_dir=job["out_dir"], progress=False, resolution=job["resolution"],
                                 max_iters=job["max_iters"], **job["params"])
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
    for s in sorted(shapes, key=lambda s: s.procedural and s.role == "train"):
        if s.name in dropped:
            s.status, s.info = "dropped", {"status": "dropped (flow budget of an earlier run)"}
        elif _complete(s.traj, s.stages):
            man = json.loads((s.traj / "manifest.json").read_text())
            s.status, s.info = "done", {"status": "skipped (done)", "t": [round(r["t"], 4) for r in man["stages"]]}
        else:
            jobs.append({"name": s.name, "source": str(s.source), "stages": s.stages, "faces": s.faces,
                         "resolution": s.resolution, "max_iters": config.max_iters, "device": device,
                         "params": ({} if config.substage_budget is None
                                    else {"substage_budget": config.substage_budget}),
                         "out_dir": str(s.traj), "recipe": s.recipe, "optional": s.procedural and s.role == "train"})
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


def _flow_budgets(shapes: list[_Shape]) -> dict:
    """The stage budgets of every finished trajectory (issue 21; :func:`vnc_warp.trajectory.budget_summary`), read
    from the manifests: what the flows of the run did, kept with its results."""
    from vnc_warp.trajectory import budget_summary, read_manifest

    out = {}
    for s in shapes:
        stages = read_manifest(s.traj / "manifest.json")["stages"]
        out[s.name] = budget_summary(stages, len(stages) - 1)
    return out


def _last_step(run: Path) -> int:
    from .checkpoint import load_checkpoint

    ckpt = run / "checkpoints" / "last.pt"
    return int(load_checkpoint(ckpt)["step"]) if ckpt.is_file() else 0


def _scaled(cfg: TrainConfig, total: int) -> TrainConfig:
    """``cfg`` with ``total`` steps: the KL warm-up, given for the nominal length, scales with it; the learning-rate
    warm-up keeps its length (at most a fifth of the run)."""
    ratio = total / cfg.optim.total_steps
    cfg.optim = dataclasses.replace(cfg.optim, total_steps=total,
                                    warmup_steps=max(1, min(cfg.optim.warmup_steps, total // 5)))
    cfg.loss = dataclasses.replace(cfg.loss, kl_warmup_start=round(cfg.loss.kl_warmup_start * ratio),
                                   kl_warmup_steps=round(cfg.loss.kl_warmup_steps * ratio))
    return cfg


def _rows(run: Path) -> list[dict]:
    path = run / "log.jsonl"
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()] if path.is_file() else []


def _train(kind: str, cfg: TrainConfig, dataset, run: Path, *, device: str | None, budget_s: float | None,
           config: ExperimentConfig, progress: bool, log: Callable[[str], None], deadline: float | None = None,
           fork_at: float | None = None) -> dict:
    """Train one model to its planned step count (resuming, or skipping when done) and summarize it.

    The budget is the model's in all: the calibration turns it into a step count once (``plan.json``), and every
    call adds its seconds to the plan's. ``deadline`` (a :func:`time.monotonic` time) stops the training after
    the calibration with a checkpoint; the summary's ``finished`` is then False and the same call resumes.
    ``fork_at`` (a fraction of the planned steps) keeps a copy of the checkpoint of that step as ``fork.pt``
    (:attr:`ExperimentConfig.cvae1_fork`).
    """
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
    fork = run / "fork.pt"
    if fork_at is not None:
        plan["fork_step"] = int(np.clip(round(fork_at * plan["total_steps"]), plan.get("calibration_steps", 1),
                                        plan["total_steps"]))
        if done > plan["fork_step"] and not fork.is_file():
            raise ValueError(f"{run}: the VAE is at step {done}, past the step {plan['fork_step']} C-VAE-I starts "
                             "from (cvae1_fork), and has no fork.pt: train it again in a new work folder")
    if done < cfg.optim.total_steps:
        log(f"  {kind}: training to step {cfg.optim.total_steps} (from {done}), budget "
            f"{'none' if budget_s is None else f'{budget_s:.0f} s'}"
            + ("" if fork_at is None else f", C-VAE-I starts from step {plan['fork_step']}"))
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                # the calibration ran under the nominal schedule; the planned one taking over is the design
                warnings.filterwarnings("ignore", message="resume at step .* schedule settings changed")
                if fork_at is not None and not fork.is_file():
                    if done < plan["fork_step"]:
                        train(cfg, data=dataset, out_dir=run, device=device, resume=done > 0, deadline=deadline,
                              stop_at=plan["fork_step"], progress=progress)
                    if _last_step(run) == plan["fork_step"]:
                        tmp = fork.with_suffix(".tmp")
                        shutil.copyfile(run / "checkpoints" / "last.pt", tmp)
                        os.replace(tmp, fork)
                if fork_at is None or fork.is_file():
                    train(cfg, data=dataset, out_dir=run, device=device, resume=_last_step(run) > 0,
                          deadline=deadline, progress=progress)
        finally:  # an interrupted run's seconds count too
            plan["seconds"] = plan.get("seconds", 0.0) + seconds + time.perf_counter() - t0
            plan_path.write_text(json.dumps(plan, indent=1))
    else:
        plan["seconds"] = plan.get("seconds", 0.0) + seconds
        plan_path.write_text(json.dumps(plan, indent=1))
    done = _last_step(run)
    if done < cfg.optim.total_steps:
        log(f"  {kind}: stopped at the time limit at step {done} of {cfg.optim.total_steps} (checkpoint written)")
    rows = _rows(run)
    steady = [r["samples_per_s"] for r in rows[1:]] or [r["samples_per_s"] for r in rows]
    tail = rows[-max(1, len(rows) // 10):]
    final = {k: float(np.mean([r[k] for r in tail if r.get(k) is not None])) if any(r.get(k) is not None for r in tail)
             else None for k in _LOGGED}
    return {"steps": cfg.optim.total_steps, "done_steps": done, "finished": done >= cfg.optim.total_steps,
            "batch_size": cfg.data.batch_size, "seconds": plan["seconds"],
            "samples_per_s": cfg.optim.total_steps * cfg.data.batch_size / max(plan["seconds"], 1e-9),
            "steady_samples_per_s": float(np.median(steady)) if steady else math.nan,
            "final": final, "budget_s": plan.get("budget_s"), "items": len(dataset),
            **({"fork_step": plan["fork_step"]} if "fork_step" in plan else {}),
            "curve": {k: [[r["step"], r.get(k)] for r in rows[:: max(1, len(rows) // 200)]] for k in ("tsdf", "eval_tsdf")}}


# log.jsonl columns summarized (mean of the last tenth of the run) in results.json
_LOGGED = ("loss", "tsdf", "eval_tsdf", "kl", "eik", "surf", "normal", "beta_kl")


def _param_count(model: torch.nn.Module) -> dict[str, int]:
    return {"total": sum(p.numel() for p in model.parameters()),
            "trainable": sum(p.numel() for p in model.parameters() if p.requires_grad)}


def _stage_times(traj_dir: Path, times: tuple[float, ...]) -> list[float]:
    """The measured t (Eq. (7)) of the ground-truth stage nearest each of ``times``, in the same order.

    Every model is queried at these, not at the nominal ``times``: a prediction is scored against the stage
    nearest its nominal t, so it is asked for that stage's own t (the last stage's t is above 0, and a query at
    t = 0 would ask every model for a shape below the end of its training trajectories).
    """
    from .data import read_trajectory

    gt_t = np.array([s.t for s in read_trajectory(traj_dir).stages])
    return [float(gt_t[int(np.argmin(np.abs(gt_t - t)))]) for t in times]


def _eval_job(job: dict) -> dict:
    """Score the prediction of one folder nearest ``job["t"]`` (every one when it is None) against its trajectory,
    without the sampling floors, or compute the trajectory's floors once (``job["pred"]`` None); module-level for
    the process pool.

    Each scored entry gets ``t_nominal``: the time of ``job["times"]`` it was queried for (``job["queried"]``, the
    trajectory's :func:`_stage_times`, read once by the caller).
    """
    from .metrics import evaluate_trajectory, read_prediction_dir, sampling_floors

    queried = job["queried"]
    if job["pred"] is None:
        report = sampling_floors(job["gt"], queried, n_points=job["n_points"], n_emd=job["n_emd"], seed=job["seed"])
    else:
        preds, _ = read_prediction_dir(job["pred"])
        if job.get("t") is not None:  # one prediction of the folder: the one nearest t
            t = min(preds, key=lambda q: abs(q - job["t"]))
            preds = {t: preds[t]}
        report = evaluate_trajectory(preds, job["gt"], pred_frame="world", n_points=job["n_points"],
                                     n_emd=job["n_emd"], seed=job["seed"], floors=False)
        for entry in report["per_t"]:
            entry["t_nominal"] = [t for t, q in zip(job["times"], queried) if abs(q - entry["t"]) < 1e-9]
    tmp = Path(job["out"] + ".tmp")
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, job["out"])
    return report


def _with_floors(report: dict, floors: dict) -> dict:
    """``report`` of :func:`_eval_job` with the trajectory's sampling floors put where
    :func:`~vnc_warp.training.metrics.evaluate_trajectory` puts them."""
    for entry in report["per_t"]:
        if "error" not in entry:
            entry["floor"] = floors["stages"][str(entry["stage"])]
    report["sampling_floor"] = floors["stage0"]
    return report


def _predicted(folder: Path, times: list[float]) -> bool:
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
    """Mean scores per (group, method) and t over the group's trajectories: the whole prediction (package frame
    and ``unit_box``), its ``largest`` component, and the sampling ``floor`` of the scored stages."""
    def mean(values):
        return float(np.mean(values)) if values else math.nan

    def scores(entries):
        row = {k: mean([e[k] for e in entries]) for k in _SCORES}
        row["unit_box"] = {k: mean([e["unit_box"][k] for e in entries]) for k in _SCORES}
        return row

    out = {}
    for group, names in groups.items():
        out[group] = {}
        for method in methods[group]:
            per_t = []
            for t in sorted(times, reverse=True):
                entries = [next(e for e in reports[method][n]["per_t"] if any(abs(v - t) < 1e-9 for v in e["t_nominal"]))
                           for n in names if n in reports.get(method, {})]
                ok = [e for e in entries if "error" not in e]
                row = {"t": t, "n": len(entries), "failed": len(entries) - len(ok), **scores(ok),
                       "largest": scores([e["largest"] for e in ok]), "floor": scores([e["floor"] for e in ok]),
                       "components": [e.get("components") for e in entries], "t_gt": [e["t_gt"] for e in entries],
                       "t_queried": [e["t"] for e in entries]}
                per_t.append(row)
            ok_rows = [r for r in per_t if r["n"] > r["failed"]]
            out[group][method] = {"trajectories": [n for n in names if n in reports.get(method, {})],
                                  "per_t": per_t, "mean": {k: mean([r[k] for r in ok_rows]) for k in _SCORES},
                                  "failed": sum(r["failed"] for r in per_t)}
    return out


_SCORES = ("cd_x1e4", "emd_x1e2", "nce")


def _montage(path: Path, traj_dir: Path, rows: dict[str, Path], times: tuple[float, ...], size: int,
             device: str | None) -> str:
    """Ground truth and each method's meshes (rows) at each t (columns), one camera for all frames."""
    from vnc_warp.render import Camera, montage, render_mesh, save_png

    from .data import read_trajectory
    from .metrics import read_prediction_dir

    traj = read_trajectory(traj_dir)
    order = sorted(times, reverse=True)
    gt_t = np.array([s.t for s in traj.stages])
    nearest = [int(np.argmin(np.abs(gt_t - t))) for t in order]
    gt = [traj.load_stage(i) for i in nearest]
    queried = [float(gt_t[i]) for i in nearest]  # the t each model was asked for (_stage_times)
    camera = Camera.fit(gt[0], azimuth=30.0, elevation=20.0)
    frames, labels = [], []
    for m, t in zip(gt, queried):
        frames.append(render_mesh(m, camera=camera, width=size, height=size, device=device))
        labels.append(f"GT {t:.2f}")
    blank = np.full((size, size, 3), 255, dtype=np.uint8)
    for label, folder in rows.items():
        preds, _ = read_prediction_dir(folder)
        for t in queried:
            mesh = preds[min(preds, key=lambda k: abs(k - t))] if preds else None
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
    # one reference column per decoded t: the stage nearest in t, as the scores pair them, so columns align
    near = [min(range(len(traj.stages)), key=lambda i: abs(traj.stages[i].t - t)) for t in order]
    decoded_trajectory([None if preds[t] is None else load_mesh(preds[t]) for t in order], order, path,
                       reference=[traj.load_stage(i) for i in near],
                       reference_t=[traj.stages[i].t for i in near], frame_size=config.render_size,
                       title=f"Fig. 9b  {METHODS[kind]} on {role} {shape.name}", device=device)
    return str(path)


def run_experiment(config: ExperimentConfig, *, out_dir: str | os.PathLike, work_dir: str | os.PathLike,
                   meshes_dir: str | os.PathLike | None = None, device: str | None = None, progress: bool = True,
                   log: Callable[[str], None] = print, step: int | None = None) -> dict:
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
        step: run the stages up to the end of step ``step`` of :data:`STEPS` (1 data, 2 train, 3 generate,
            4 report) and stop; None: all of them.

    Returns:
        The content of ``results.json`` (step 4 or None), else a summary of what the step did.

    Raises:
        FileNotFoundError: a real mesh file is missing.
        ValueError: invalid config or step, a work folder made with other settings, or nothing left to train
            or evaluate after failed flows.
    """
    if step is not None and step not in STEPS:
        raise ValueError(f"step must be one of {sorted(STEPS)} ({', '.join(STEPS.values())}), got {step}")
    deadline = None if config.max_minutes is None else time.monotonic() + 60.0 * config.max_minutes
    threads = torch.get_num_threads()
    if config.torch_threads is not None:
        torch.set_num_threads(config.torch_threads)
    try:
        return _run(config, Path(out_dir), Path(work_dir), meshes_dir, device, progress, log, step or max(STEPS),
                    deadline)
    finally:
        torch.set_num_threads(threads)


def _run(config: ExperimentConfig, out: Path, work: Path, meshes_dir: str | os.PathLike | None, device: str | None,
         progress: bool, log: Callable[[str], None], last_step: int, deadline: float | None) -> dict:
    import vnc_warp._device  # noqa: F401  (quiet Warp first)
    import warp as wp

    from .data import build_dataset

    config.validate()
    _check_work_dir(work, config)
    clock = _Clock(work / "timings.json")
    meshes = Path(meshes_dir) if meshes_dir is not None else default_meshes_dir()
    torch_device = _torch_device(device)
    warp_device = device if device is not None else ("cuda:0" if torch_device.type == "cuda" else "cpu")
    results: dict[str, Any] = {"experiment": config.to_dict(), "notes": []}
    notes = results["notes"]

    # step 1: data
    with clock.stage("flows", log):
        shapes = _shapes(config, work, meshes)
        _flows(shapes, config, warp_device, work, log)
    results["flows"] = {s.name: {"kind": s.kind, "role": s.role, **s.info} for s in shapes}
    ok = [s for s in shapes if s.status == "done"]
    results["flow_budgets"] = _flow_budgets(ok)
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
    distill = next((s for s in ok if config.distill_mesh and s.name == Path(config.distill_mesh).stem), None)
    if config.distill_mesh and distill is None:
        notes.append(f"C-VAE-II skipped: the flow of {config.distill_mesh} failed")
    with clock.stage("dataset", log):
        in_data = [*train_shapes, *([distill] if distill is not None and distill.role == "holdout" else [])]
        ns, nu, nn_ = config.num_samples
        stamp = work / "data" / "built.json"
        names = sorted(s.name for s in in_data)
        if stamp.is_file() and json.loads(stamp.read_text()).get("shapes") == names:
            results["dataset"] = json.loads(stamp.read_text())
        else:
            results["dataset"] = build_dataset([s.traj for s in in_data], work / "data", num_surface=ns,
                                               num_uniform=nu, num_near=nn_, num_reference=config.num_reference,
                                               grid_resolution=config.grid_resolution,
                                               noise=config.noise,
                                               truncation=config.truncation, device=warp_device, seed=config.seed,
                                               progress=progress)
            results["dataset"]["shapes"] = names
            stamp.write_text(json.dumps(results["dataset"]))
    if last_step == 1:
        return _step_summary(1, results, clock, log)

    # step 2: C-VAE-I and the VAE; step 3 begins with C-VAE-II
    training = {}
    runs = work / "runs"
    not_trained = () if distill is None or distill.role == "train" else (distill.name,)
    unfinished: list[str] = []
    started = False  # a model trained in this call: the first one always starts, so that every call gets on
    fork = config.cvae1_fork
    for kind in ("cvae1", "vae", "cvae2") if fork is None else ("vae", "cvae1", "cvae2"):
        if kind == "cvae2" and (distill is None or last_step < 3):
            continue
        if unfinished:
            unfinished.append(kind)
            continue
        start = runs / "vae" / ("fork.pt" if kind == "cvae1" else "checkpoints/last.pt")
        cfg = run_config(config, kind, pretrained=str(start.resolve()))
        if config.data_workers is not None:
            cfg.data = dataclasses.replace(cfg.data, num_workers=config.data_workers)
        budget = config.distill_budget_s if kind == "cvae2" else config.train_budget_s
        if kind == "cvae1" and fork is not None:
            # the steps before the fork are the VAE's and C-VAE-I's both: the rest of the same budget is its own
            budget = None if budget is None else (1.0 - fork) * budget
            cfg = _scaled(cfg, max(1, round((1.0 - fork) * cfg.optim.total_steps)))
        if (started and deadline is not None and not _trained(runs / kind)
                and deadline - time.monotonic() < min(_MIN_START_S, 15.0 * config.max_minutes)):
            log(f"  {kind}: not started, {max(deadline - time.monotonic(), 0.0):.0f} s left of the time limit")
            unfinished.append(kind)
            continue
        with clock.stage(f"train_{kind}", log):
            started = started or not _trained(runs / kind)
            training[kind] = _train(kind, cfg, _dataset(kind, cfg, config, work, distill, not_trained), runs / kind,
                                    device=str(torch_device), budget_s=budget, config=config, progress=progress,
                                    log=log, deadline=deadline, fork_at=fork if kind == "vae" else None)
        if kind == "cvae1" and fork is not None:
            training[kind]["starts_from"] = {"model": "vae", "step": training["vae"]["fork_step"]}
        if not training[kind]["finished"]:
            unfinished.append(kind)
    results["training"] = training
    if unfinished:
        return _step_summary(last_step, results, clock, log, unfinished=unfinished)
    if last_step == 2:
        return _step_summary(2, results, clock, log)

    # step 3: generation
    from .model import load_model

    models = {kind: load_model(runs / kind, device=torch_device) for kind in training}
    for kind, (model, _) in models.items():
        training[kind]["parameters"] = _param_count(model)
    both = [*holdout, *([distill] if distill is not None and distill.role == "train" else [])]
    targets = {"cvae1": both, "baseline": both, "cvae2": [distill] if "cvae2" in models else []}
    preds = work / "pred"
    with clock.stage("generate", log):
        left = _generate(targets, models, preds, config, deadline)
    if left:
        return _step_summary(last_step, results, clock, log, unfinished=[f"generate ({left} left)"])
    if last_step == 3:
        return _step_summary(3, results, clock, log)

    # step 4: evaluation, latent anatomy, results, figures
    with clock.stage("evaluate", log):
        results["evaluation"], left = _evaluate(targets, holdout, distill, preds, work, config, log, deadline)
    if left:
        return _step_summary(last_step, results, clock, log, unfinished=[f"evaluate ({left} jobs left)"])
    with clock.stage("latent_anatomy", log):
        results["latent_anatomy"] = _anatomy(models, holdout, out, config, notes)
    results["environment"] = {"device": str(torch_device), "torch": torch.__version__, "warp": wp.__version__,
                              "python": platform.python_version(),
                              "gpu": torch.cuda.get_device_name(torch_device) if torch_device.type == "cuda" else None}
    notes.append("latent interp. (VAE): the plain VAE (same backbone and training budget as C-VAE-I) encodes the "
                 "ground-truth stage 0 and LAST stage and decodes their linear blend; it is given the final shape, the "
                 "C-VAEs only stage 0")
    notes.append("each column t is scored against the ground-truth stage nearest in t, and every model is queried "
                 "at that stage's measured t (t = 0 -> the last stage, whose measured t is > 0; t_queried in "
                 "results.json)")
    if distill is not None:
        notes.append(f"{distill.name}: C-VAE-II is trained on its trajectory alone"
                     + (" (C-VAE-I and the VAE never saw it)" if distill.role == "holdout" else
                        " (also a training shape of C-VAE-I and the VAE)"))
    results["checks"] = check_results(results)
    results["figures"] = []
    _write_results(out, results, clock)  # the numbers are safe before any figure is drawn
    if config.figures:
        with clock.stage("figures", log):
            _figures(results, holdout, distill, preds, out, config, warp_device, notes)
        _write_results(out, results, clock)
    log(f"[experiment] done in {clock.total():.1f} s: {out / 'results.json'}, {out / 'results.md'}")
    return results


def _torch_device(device: str | None) -> torch.device:
    from .train import resolve_device

    return resolve_device(device)


def _step_summary(step: int, results: dict, clock: _Clock, log: Callable[[str], None], *,
                  unfinished: list[str] | None = None) -> dict:
    """What a call did; ``unfinished`` names what the time limit left for the next call (then logged so)."""
    summary = {"step": step, "name": STEPS[step], "timings_s": {**clock.seconds, "total": clock.total()},
               "notes": results["notes"], "unfinished": unfinished or []}
    if "training" in results:
        summary["training"] = {k: {"steps": v["steps"], "done_steps": v["done_steps"], "seconds": v["seconds"],
                                   "final": v["final"], **{x: v[x] for x in ("fork_step", "starts_from") if x in v}}
                               for k, v in results["training"].items()}
    if unfinished:
        log(f"[experiment] step {step} ({STEPS[step]}) NOT finished after {clock.total():.1f} s (time limit "
            f"{results['experiment']['max_minutes']} min): {', '.join(unfinished)} left; run the same command "
            "again to go on from the checkpoints")
    else:
        log(f"[experiment] step {step} ({STEPS[step]}) done in {clock.total():.1f} s")
    return summary


def _trained(run: Path) -> bool:
    """The model of ``run`` reached its planned step count (``plan.json``) in an earlier call."""
    plan = run / "plan.json"
    return plan.is_file() and _last_step(run) >= json.loads(plan.read_text()).get("total_steps", math.inf)


def _dataset(kind: str, cfg: TrainConfig, config: ExperimentConfig, work: Path, distill: _Shape | None,
             not_trained: tuple[str, ...]):
    """The training items of one model: C-VAE-I and the VAE every training shape (not a held-out distilled
    one), C-VAE-II the distilled trajectory alone; preloaded, so that data-loader workers share the arrays."""
    from .data import TrajectoryDataset

    kw = dict(num_surface=cfg.data.num_surface, num_queries=cfg.data.num_queries, near_fraction=cfg.data.near_fraction,
              num_on_surface=cfg.data.num_on_surface, fresh_fraction=cfg.data.fresh_fraction, seed=cfg.seed,
              cache=True)
    if kind == "cvae2":
        data = TrajectoryDataset(work / "data", split="test", holdout=(distill.name,), repeats=config.distill_repeats,
                                 **kw)
    else:
        data = TrajectoryDataset(work / "data", split="train", holdout=not_trained, repeats=config.repeats, **kw)
    data.preload()
    return data


def _generate(targets: dict[str, list[_Shape]], models: dict, preds: Path, config: ExperimentConfig,
              deadline: float | None = None) -> int:
    """Write the missing predictions; past ``deadline`` none is started. Returns how many are left."""
    from .baseline import latent_interpolation
    from .data import read_trajectory
    from .inference import predict_times

    todo = [(m, s, sorted(set(_stage_times(s.traj, config.times)), reverse=True))
            for m, trajs in targets.items() for s in trajs]
    todo = [(m, s, q) for m, s, q in todo if not _predicted(preds / m / s.name, q)]
    for k, (method, s, queried) in enumerate(todo):
        if deadline is not None and time.monotonic() >= deadline:
            return len(todo) - k
        folder = preds / method / s.name
        if method == "baseline":
            model, cfg = models["vae"]
            latent_interpolation(model, s.traj, queried, folder, resolution=config.resolution,
                                 num_surface=cfg.data.num_surface, seed=config.seed)
        else:
            model, cfg = models[method]
            predict_times(model, read_trajectory(s.traj).load_stage(0), queried, folder,
                          num_surface=cfg.data.num_surface, resolution=config.resolution, seed=config.seed,
                          name=s.name, meta={"method": method})
    return 0


_GROUPS = {"humanoid": "held-out humanoids", "blob": "held-out blobs", "real": "held-out real"}


def _evaluate(targets: dict[str, list[_Shape]], holdout: list[_Shape], distill: _Shape | None, preds: Path, work: Path,
              config: ExperimentConfig, log: Callable[[str], None] = lambda _: None,
              deadline: float | None = None) -> tuple[dict | None, int]:
    """Score every prediction (one job per method, trajectory and t: ~5x as many jobs as folders, so that the
    workers stay busy to the end) and every scored trajectory's sampling floors (one job per trajectory: the
    methods share them); each job's report is cached in ``work/eval`` as it ends, so an interrupted call resumes
    with the jobs left. Past ``deadline`` (:func:`time.monotonic`) no job is started; the ones running end.

    Returns:
        ``(evaluation, 0)``, or ``(None, jobs left)`` when the deadline came first.
    """
    from .metrics import combine_reports

    jobs, reports, floors = [], {m: {} for m in targets}, {}
    (work / "eval").mkdir(parents=True, exist_ok=True)
    trajectories = {s.name: s for trajs in targets.values() for s in trajs}
    # the measured t each nominal t is asked at, per trajectory (reading one verifies its stage files' checksums)
    score = {name: {"n_points": config.n_points, "n_emd": config.n_emd, "seed": config.seed,
                    "times": list(config.times), "queried": _stage_times(s.traj, config.times)}
             for name, s in trajectories.items()}
    for name, s in trajectories.items():
        path = work / "eval" / f"floor__{name}.json"
        if path.is_file():
            floors[name] = json.loads(path.read_text())
        else:
            jobs.append((None, name, {"pred": None, "gt": str(s.traj), **score[name], "out": str(path)}))
    parts: dict[tuple[str, str], list] = {}
    for method, trajs in targets.items():
        for s in trajs:
            queried = sorted(set(score[s.name]["queried"]), reverse=True)  # two t, one stage: once
            parts[method, s.name] = [None] * len(queried)
            for k, t in enumerate(queried):
                path = work / "eval" / f"{method}__{s.name}__t{k}.json"
                if path.is_file():
                    parts[method, s.name][k] = json.loads(path.read_text())
                else:
                    jobs.append(((method, k, t), s.name, {"pred": str(preds / method / s.name), "gt": str(s.traj),
                                                          **score[s.name], "t": t, "out": str(path)}))
    t0, done = time.perf_counter(), 0

    def finished(key, n, report):
        nonlocal done
        done += 1
        if key is None:
            floors[n] = report
        else:
            parts[key[0], n][key[1]] = report
        what = "floors" if key is None else f"{key[0]} at t = {key[2]:.3f}"
        log(f"  scored {what} of {n} ({done} of {len(jobs)}, {time.perf_counter() - t0:.0f} s)")

    def late() -> bool:
        return deadline is not None and time.monotonic() >= deadline

    if config.eval_workers > 1 and len(jobs) > 1:
        ctx = multiprocessing.get_context("spawn")
        with cf.ProcessPoolExecutor(max_workers=min(config.eval_workers, len(jobs)), mp_context=ctx) as pool:
            futures = {pool.submit(_eval_job, job): (m, n) for m, n, job in jobs}
            for fut in cf.as_completed(futures):
                if not fut.cancelled():
                    finished(*futures[fut], fut.result())
                if late():
                    for other in futures:
                        other.cancel()  # the ones not started; the running ones end and are kept
    else:
        for m, n, job in jobs:
            if late():
                break
            finished(m, n, _eval_job(job))
    if done < len(jobs):
        log(f"  scoring stopped at the time limit: {len(jobs) - done} of {len(jobs)} jobs left")
        return None, len(jobs) - done
    for (m, n), rs in parts.items():
        reports[m][n] = _with_floors(combine_reports(rs), floors[n])
    groups = {label: [s.name for s in holdout if s.kind == kind] for kind, label in _GROUPS.items()}
    methods = {g: ["cvae1", "baseline"] for g in groups}
    if distill is not None:
        groups[f"distilled: {distill.name}"] = [distill.name]
        methods[f"distilled: {distill.name}"] = [m for m in ("cvae2", "cvae1", "baseline") if targets[m]]
    groups = {g: names for g, names in groups.items() if names}
    evaluation = {
        "groups": _aggregate(reports, groups, methods, config.times),
        "per_trajectory": {m: {n: {"per_t": r["per_t"], "mean": r["mean"], "failed": r["failed"]}
                               for n, r in rs.items()} for m, rs in reports.items()},
        "sampling_floor": {n: r["sampling_floor"] for n, r in reports["cvae1"].items()},
        "conventions": next(iter(reports["cvae1"].values()))["conventions"],
    }
    return evaluation, 0


def _anatomy(models: dict, holdout: list[_Shape], out: Path, config: ExperimentConfig, notes: list[str]) -> dict:
    from .latent import latent_anatomy

    anatomy = {}
    model, cfg = models["cvae1"]
    kwargs = dict(title="C-VAE-I", num_surface=cfg.data.num_surface, seed=config.seed)
    trajs = [s.traj for s in holdout]
    try:
        anatomy["cvae1"] = latent_anatomy(model, trajs, **kwargs,
                                          figure=out / "fig11_latent_space.png" if config.figures else None)
    except Exception as exc:  # a figure must not cost the numbers
        notes.append(f"Fig. 11 not drawn: {type(exc).__name__}: {exc}")
        anatomy["cvae1"] = latent_anatomy(model, trajs, **kwargs)
    model, cfg = models["vae"]
    anatomy["vae"] = latent_anatomy(model, trajs, title="VAE", num_surface=cfg.data.num_surface, seed=config.seed,
                                    use_umap=False)
    return anatomy


def _figures(results: dict, holdout: list[_Shape], distill: _Shape | None, preds: Path, out: Path,
             config: ExperimentConfig, device: str | None, notes: list[str]) -> None:
    """At most five PNGs beside results.json and results.md (Fig. 11 is drawn with the anatomy)."""
    figs = results["figures"]
    if "fig11" in results["latent_anatomy"]["cvae1"].get("plots", {}):
        figs.append(results["latent_anatomy"]["cvae1"]["plots"]["fig11"])
    picks = ([s for s in holdout if s.kind == "real" and s is not distill][:1]
             + [s for s in holdout if s.kind == "humanoid"][:1]) or holdout[:1]
    shown = [(s, "cvae1") for s in picks]
    if distill is not None and "cvae2" in results["training"]:
        shown.insert(0, (distill, "cvae2"))
    for s, kind in shown:
        rows = {_SHORT[m]: preds / m / s.name for m in (kind, "baseline")}
        try:
            figs.append(_montage(out / f"compare_{s.name}.png", s.traj, rows, config.times, config.render_size, device))
        except Exception as exc:  # a figure must not cost the numbers
            notes.append(f"figure of {s.name} not drawn: {type(exc).__name__}: {exc}")
    for s in picks[:1]:
        try:
            figs.append(_fig9b(out / f"fig9b_cvae1_{s.name}.png", s, preds / "cvae1" / s.name, "cvae1", config, device))
        except Exception as exc:  # a figure must not cost the numbers
            notes.append(f"Fig. 9b of {s.name} not drawn: {type(exc).__name__}: {exc}")
    try:
        figs.append(_training_figure(out / "training.png", results["training"]))
    except Exception as exc:  # a figure must not cost the numbers
        notes.append(f"training curves not drawn: {type(exc).__name__}: {exc}")


def _training_figure(path: Path, training: dict) -> str:
    """L_tsdf decoded from posterior samples (training) and from the posterior mean (eval mode), per model."""
    from vnc_warp.plot import line_plot

    series = {}
    for kind, tr in training.items():
        for key, label in (("tsdf", "train, sampled code"), ("eval_tsdf", "eval, mean code")):
            pts = [(st, v) for st, v in tr["curve"][key] if v is not None and v > 0]
            if pts:
                x, y = np.asarray(pts, dtype=np.float64).T
                series[f"{MODELS[kind].split(' ')[0]}: {label}"] = (x, np.log10(y))
    line_plot(series, title="L_tsdf during training:\nsampled codes (training) vs posterior mean (inference)",
              xlabel="step", ylabel="log10 L_tsdf", path=path, size=(1100, 520), legend="outside")
    return str(path)


def _write_results(out: Path, results: dict, clock: _Clock) -> None:
    out.mkdir(parents=True, exist_ok=True)
    results["timings_s"] = clock.totals()
    results["timings_this_call_s"] = {**clock.seconds, "total": clock.total()}
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


def _ok(x: Any) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


def check_results(results: dict) -> list[dict]:
    """The "done when" claims of issue 24, each measured against this run's numbers (never asserted).

    Returns:
        One ``{"claim", "target", "value", "met"}`` per claim: C-VAE-II on the distilled trajectory (CD within 3x
        the sampling floor of the scored stage and below latent interpolation at every t, NCE at t = 1 <= 0.3);
        C-VAE-I (no failed decode; below latent interpolation at every t on the held-out real meshes and the
        held-out humanoids); the radial structure (pooled r(norm, t) >= 0.5; one principal component with
        r >= 0.8 inside every held-out trajectory, one sign for all).
    """
    checks = []
    groups = results["evaluation"]["groups"]

    def add(claim: str, target: str, value: Any, met: bool) -> None:
        checks.append({"claim": claim, "target": target, "value": value, "met": bool(met)})

    for group, rows in groups.items():
        if not group.startswith("distilled") or "cvae2" not in rows:
            continue
        mine, base = rows["cvae2"]["per_t"], rows["baseline"]["per_t"]
        ratios = [r["cd_x1e4"] / r["floor"]["cd_x1e4"] if _ok(r["cd_x1e4"]) and _ok(r["floor"]["cd_x1e4"])
                  else math.nan for r in mine]
        add(f"C-VAE-II ({group}): CD <= 3x sampling floor at every t", "<= 3 at each t",
            {r["t"]: x for r, x in zip(mine, ratios)}, all(_ok(x) and x <= 3.0 for x in ratios))
        add(f"C-VAE-II ({group}): CD below latent interpolation at every t", "C-VAE-II < interp. at each t",
            {a["t"]: [a["cd_x1e4"], b["cd_x1e4"]] for a, b in zip(mine, base)},
            all(_ok(a["cd_x1e4"]) and (not _ok(b["cd_x1e4"]) or a["cd_x1e4"] < b["cd_x1e4"]) for a, b in zip(mine, base)))
        at1 = next((r for r in mine if r["t"] == 1.0), None)
        if at1 is not None:
            add(f"C-VAE-II ({group}): NCE at t = 1", "<= 0.3 rad", at1["nce"], _ok(at1["nce"]) and at1["nce"] <= 0.3)
    failed = sum(rows["cvae1"]["failed"] for rows in groups.values() if "cvae1" in rows)
    add("C-VAE-I: failed decodes", "0", failed, failed == 0)
    for group in ("held-out real", "held-out humanoids"):
        if group not in groups:
            continue
        mine, base = groups[group]["cvae1"]["per_t"], groups[group]["baseline"]["per_t"]
        add(f"C-VAE-I ({group}): CD below latent interpolation at every t", "C-VAE-I < interp. at each t",
            {a["t"]: [a["cd_x1e4"], b["cd_x1e4"]] for a, b in zip(mine, base)},
            all(_ok(a["cd_x1e4"]) and (not _ok(b["cd_x1e4"]) or a["cd_x1e4"] < b["cd_x1e4"]) for a, b in zip(mine, base)))
    anatomy = results.get("latent_anatomy", {}).get("cvae1")
    if anatomy is not None:
        r = anatomy["norm_t_pearson"]
        add("radial structure: pooled r(latent norm, t) on held-out trajectories", ">= 0.5", r, _ok(r) and r >= 0.5)
        best = anatomy["best_pc"]
        add(f"radial structure: PC{best['pc']} orders every held-out trajectory by t (one sign)",
            "r >= 0.8 in every trajectory", best.get("within"), _ok(best.get("min_within")) and best["min_within"] >= 0.8)
    return checks


def _cd_table(groups: dict, times: list[float], key: str, title: str, part: str | None) -> list[str]:
    lines = [f"## {title} (lower is better)", "",
             "| trajectories | method | " + " | ".join(f"t={t:g}" for t in times) + " | failed |",
             "|---|---|" + "---|" * (len(times) + 1)]
    for group, rows in groups.items():
        for method, row in rows.items():
            by_t = {r["t"]: (r if part is None else r[part]) for r in row["per_t"]}
            cells = [_fmt(by_t[t][key]) if t in by_t else "n/a" for t in times]
            lines.append(f"| {group} ({len(row['trajectories'])}) | {METHODS[method]} | " + " | ".join(cells)
                         + f" | {row['failed']} |")
        floors = {r["t"]: (r["floor"] if part != "unit_box" else r["floor"]["unit_box"])[key]
                  for r in next(iter(rows.values()))["per_t"]}
        lines.append(f"| {group} | *sampling floor* | " + " | ".join(_fmt(floors.get(t)) for t in times) + " | |")
    return lines + [""]


def results_markdown(results: dict) -> str:
    """The tables of a ``results.json`` as Markdown."""
    exp = results["experiment"]
    lines = [f"# C-VAE experiment `{exp['name']}`", "",
             f"Marching cubes {exp['resolution']}^3; CD and NCE on {exp['n_points']:,} points per surface, EMD on "
             f"{exp['n_emd']:,}; package frame (the ground truth's stage-0 box at max extent 1.8) unless marked. "
             "Each group's last row is the sampling floor: the scored ground-truth stages against themselves "
             "resampled at the same counts.", ""]
    checks = results.get("checks", [])
    if checks:
        lines += ["## Checks (issue 24, done when)", "", "| claim | target | value | met |", "|---|---|---|---|"]
        for c in checks:
            value = c["value"]
            if isinstance(value, dict):
                value = ", ".join(f"{k}: " + ("/".join(_fmt(x, 2) for x in v) if isinstance(v, list) else _fmt(v, 2))
                                  for k, v in value.items())
            elif isinstance(value, float):
                value = _fmt(value)
            lines.append(f"| {c['claim']} | {c['target']} | {value} | {'yes' if c['met'] else '**no**'} |")
        lines.append("")
    groups = results["evaluation"]["groups"]
    times = sorted(exp["times"], reverse=True)
    lines += _cd_table(groups, times, "cd_x1e4", "CD x1e-4, all components", None)
    lines += _cd_table(groups, times, "cd_x1e4", "CD x1e-4, largest component", "largest")
    lines += _cd_table(groups, times, "emd_x1e2", "EMD x1e-2, all components", None)
    lines += _cd_table(groups, times, "nce", "NCE (rad), all components", None)
    lines += _cd_table(groups, times, "cd_x1e4", "Unit box: CD x1e-4, all components", "unit_box")
    lines += _cd_table(groups, times, "emd_x1e2", "Unit box: EMD x1e-2, all components", "unit_box")
    lines += ["## Training", "", "| model | parameters (trainable) | items | steps | batch | seconds | samples/s "
              "(steady) | L_tsdf (sampled code) | L_tsdf (eval, mean code) | L_surf | L_normal |", "|---" * 11 + "|"]
    for kind, tr in results["training"].items():
        p, f = tr.get("parameters", {}), tr["final"]
        lines.append(f"| {MODELS[kind]} | {p.get('total', 0):,} ({p.get('trainable', 0):,}) | {tr['items']} | "
                     f"{tr['steps']} | {tr['batch_size']} | {_fmt(tr['seconds'], 1)} | "
                     f"{_fmt(tr['steady_samples_per_s'], 1)} | {_fmt(f.get('tsdf'), 5)} | {_fmt(f.get('eval_tsdf'), 5)} | "
                     f"{_fmt(f.get('surf'), 5)} | {_fmt(f.get('normal'), 4)} |")
    forked = results["training"].get("cvae1", {}).get("starts_from")
    if forked:
        lines += ["", f"C-VAE-I started from the VAE's weights at its step {forked['step']} (cvae1_fork): the steps up "
                  "to there count for both, each model's own steps after it make up the same budget."]
    lines += ["", "L_tsdf columns: mean of the last tenth of the run; the eval column decodes the posterior mean "
              "in eval mode, as inference does.", "",
              "## Latent anatomy (held-out trajectories, every stage)", "",
              "| model | encoding | samples | r(norm, t) pooled | r(norm, t) within: mean / min | best PC | "
              "its r within: min | its r pooled | PC1 r within: mean | variance of PC1..5 |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    for kind, rep in results["latent_anatomy"].items():
        best = rep["best_pc"]
        ev = ", ".join(_fmt(v, 2) for v in rep["explained_variance_ratio"])
        lines.append(f"| {MODELS[kind]} | {rep['encoding']} | {rep['n']} | {_fmt(rep['norm_t_pearson'])} | "
                     f"{_fmt(rep.get('norm_t_pearson_within'))} / {_fmt(rep.get('norm_t_min_within'))} | "
                     f"PC{best['pc']} | {_fmt(best.get('min_within'))} | {_fmt(best['pooled_r'])} | "
                     f"{_fmt(rep.get('pc1_t_pearson_within'))} | {ev} |")
    umap = [k for k, rep in results["latent_anatomy"].items() if rep.get("umap")]
    lines += ["", "UMAP (max-pooled, Fig. 11a): " + (", ".join(
        f"{MODELS[k]} r(distance from centre, t) = {_fmt(results['latent_anatomy'][k]['umap_radius_t_pearson'])}"
        for k in umap) if umap else "umap-learn not installed; Fig. 11a shows PCA instead.")]
    t = results["timings_s"]
    lines += ["", "## Wall time (s, summed over every call on the work folder)", "", "| " + " | ".join(t) + " |", "|" + "---|" * len(t),
              "| " + " | ".join(_fmt(v, 1) for v in t.values()) + " |", ""]
    flows = results["flows"]
    done = [f for f in flows.values() if f.get("status") in ("done", "skipped (done)")]
    lines += [f"Flows: {len(done)} of {len(flows)} trajectories, {exp['stages']} stages each"
              + (f" ({exp['distill_mesh']}: {exp['distill_stages']})" if exp.get("distill_stages") else "")
              + f"; environment: {results['environment']}", ""]
    budgets = results.get("flow_budgets") or {}
    if budgets:
        missed = {name: b["misses"] for name, b in budgets.items() if b["misses"]}
        lines += [f"Flow budgets (every stage within 0.02 of t = 1 - i/N, the documented exceptions out): "
                  f"{len(budgets) - len(missed)} of {len(budgets)} trajectories; worst "
                  f"{max(b['max_dt_ruled'] for b in budgets.values()):.3f}"
                  + ("; misses: " + ", ".join(f"{name} stage {i} t {t:.3f} for {target:.3f} ({status})"
                                            for name, ms in missed.items() for i, t, target, status in ms)
                     if missed else ""), ""]
    lines += ["## Notes", ""] + [f"- {n}" for n in results["notes"]] + [""]
    return "\n".join(lines)
