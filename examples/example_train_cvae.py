# SPDX-License-Identifier: Apache-2.0
"""Example: training a tiny C-VAE on a VNC-Flow trajectory.

The whole pipeline of the paper at toy size: a procedural shape flows through VNC-Flow (Algorithm 1), its
stages are sampled into a truncated-SDF dataset, and the ``tiny`` C-VAE-I configuration learns to decode
the shape at any normalized time ``t`` (Eq. 7) from the detailed input and ``t`` alone (Sec. 3.3).

Each step() trains a few more optimiser steps (resuming the run folder's checkpoint, so the run is the same
as one uninterrupted ``train``); render() decodes the input at the trajectory's times. The result is one PNG
per rendered step with the decoded shapes above the VNC-Flow stages (Fig. 9b), and the latents of the input
encoded across ``t`` in two dimensions (Fig. 11).

    python examples/example_train_cvae.py --device cpu --num-frames 2 --steps-per-frame 100
"""

import dataclasses
import json
import os
import tempfile

import numpy as np
import torch
import warp as wp

import vnc_warp as vw
from vnc_warp import figures
from vnc_warp.flow import flow
from vnc_warp.training.model import load_model
from vnc_warp.training.config import named_config
from vnc_warp.training.data import build_dataset
from vnc_warp.training.inference import decode_mesh, surface_condition
from vnc_warp.training.train import train


class Example:
    """A tiny C-VAE-I learning one procedural VNC-Flow trajectory.

    Args:
        workdir: folder for the trajectory, the dataset and the run.
        stages: VNC-Flow stages of the trajectory.
        subdivisions: resolution of the procedural shape (3: 642 vertices).
        total_steps: optimiser steps of the whole run (the learning-rate schedule's length).
        steps_per_frame: optimiser steps per step().
        resolution: marching-cubes grid of the decoded meshes; 0 renders nothing.
    """

    def __init__(self, workdir, stages=4, subdivisions=3, total_steps=200, steps_per_frame=100, resolution=48):
        self.device = wp.get_device()
        self.torch_device = "cuda" if self.device.is_cuda else "cpu"
        shape = vw.random_shape(7, subdivisions=subdivisions, name="shape_7")
        traj_dir = os.path.join(workdir, "trajectories", shape.name)
        self.trajectory = flow(shape, stages, device=self.device, out_dir=traj_dir, progress=False)
        self.data = os.path.join(workdir, "data")
        build_dataset([traj_dir], self.data, num_surface=2048, num_uniform=1024, num_near=1024, device=self.device,
                      overwrite=True, progress=False)
        self.config = named_config("tiny")
        self.config.optim = dataclasses.replace(self.config.optim, total_steps=total_steps)
        # one trajectory of N + 1 stages is the whole dataset: a batch cannot hold more
        self.config.data = dataclasses.replace(self.config.data,
                                               batch_size=min(self.config.data.batch_size, stages + 1))
        self.run = os.path.join(workdir, "run")
        self.steps_per_frame = steps_per_frame
        self.trained = 0
        self.losses = []
        self.resolution = resolution
        self.frames = []

    def step(self):
        stop = min(self.trained + self.steps_per_frame, self.config.optim.total_steps)
        train(self.config, data=self.data, out_dir=self.run, device=self.torch_device, resume=self.trained > 0,
              stop_at=stop, progress=False)
        self.trained = stop
        with open(os.path.join(self.run, "log.jsonl")) as fh:
            self.losses = [json.loads(line)["loss"] for line in fh if line.strip()]

    def model(self):
        return load_model(os.path.join(self.run, "checkpoints", "last.pt"), device=self.torch_device)[0]

    def render(self):
        if not self.resolution:
            return
        model = self.model()
        stage0 = self.trajectory.meshes[0]
        surface, center, scale = surface_condition(stage0, num_points=self.config.data.num_surface)
        decoded = []
        for t in self.trajectory.t:
            try:
                decoded.append(decode_mesh(model, surface, float(t), resolution=self.resolution, center=center,
                                           scale=scale))
            except ValueError:  # an untrained model may decode no surface at all (MeshError is a ValueError)
                decoded.append(None)
        self.frames.append(figures.decoded_trajectory(
            decoded, self.trajectory.t, reference=self.trajectory.meshes, reference_t=self.trajectory.t,
            frame_size=160, device=self.device,
            title=f"tiny C-VAE after {self.trained} steps (loss {np.mean(self.losses[-10:]):.4f})"))

    def latents(self, count=21):
        """The input's latents encoded at ``count`` times evenly in [0, 1]: (count, M, C) and (count,)."""
        model = self.model()
        surface, _, _ = surface_condition(self.trajectory.meshes[0], num_points=self.config.data.num_surface)
        t = np.linspace(0.0, 1.0, count)
        batch = torch.as_tensor(surface, device=self.torch_device).unsqueeze(0).expand(count, -1, -1)
        with torch.no_grad():
            z, _ = model.encode(batch, torch.as_tensor(t, dtype=torch.float32, device=self.torch_device),
                                sample=False)
        return z.cpu().numpy(), t

    def save(self, path):
        vw.save_png(path, vw.montage(self.frames, cols=1))
        z, t = self.latents()
        figures.latent_space(z, t, os.path.splitext(path)[0] + "_latents.png",
                             title="Fig. 11  Latents of one input encoded across t (tiny C-VAE)")


if __name__ == "__main__":
    import argparse

    parser = argparse.ArgumentParser(formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp and torch device.")
    parser.add_argument("--num-frames", type=int, default=2, help="Training rounds, each followed by a render.")
    parser.add_argument("--steps-per-frame", type=int, default=100, help="Optimiser steps per round.")
    parser.add_argument("--stages", type=int, default=4, help="VNC-Flow stages of the training trajectory.")
    parser.add_argument("--subdivisions", type=int, default=3, help="Resolution of the procedural shape.")
    parser.add_argument("--resolution", type=int, default=48, help="Decoding grid; 0 renders nothing.")
    parser.add_argument("--workdir", type=str, default=None, help="Work folder (default: a temporary one).")
    parser.add_argument("--out", type=str, default="example_train_cvae.png", help="Output PNG.")
    args = parser.parse_known_args()[0]

    with wp.ScopedDevice(args.device), tempfile.TemporaryDirectory() as tmp:
        example = Example(args.workdir or tmp, stages=args.stages, subdivisions=args.subdivisions,
                          total_steps=args.num_frames * args.steps_per_frame, steps_per_frame=args.steps_per_frame,
                          resolution=args.resolution)
        for _ in range(args.num_frames):
            example.step()
            example.render()
            print(f"step {example.trained}: loss {np.mean(example.losses[-10:]):.4f}")
        print(f"loss fell from {example.losses[0]:.4f} to {np.mean(example.losses[-10:]):.4f}")
        if args.resolution:
            example.save(args.out)
            print(f"wrote {args.out}")
