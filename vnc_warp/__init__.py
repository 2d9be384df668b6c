"""vnc-warp: the VNC operator, VNC-Flow and the C-VAE of "VNC: A Scale-Space Foundation for Learnable
3D Surface Evolution", on NVIDIA Warp kernels with PyTorch interop."""

from .mesh import EdgeTopology, Mesh, MeshError, from_arrays, load_mesh

__version__ = "0.1.0"
from .operators import edge_fields, integrated_mean_curvature, vnc_hard, vnc_soft
from .scale import ScaleCurve, adaptive_scale, default_scales, scale_curve, vnc_auc
from .shapes import icosphere, random_shape, shape_family
from .render import Camera, colorbar, colormap, montage, render_mesh, save_png
from .plot import line_plot, scatter_plot
from .sdf import sdf_grid, signed_distance
from .remesh import sdf_remesh, validate_surface
from .operators import STRATEGIES, choose_strategy
from ._replay import set_graph_replay
from . import figures
# `vw.flow` is the function (the contract); the module stays importable as `vnc_warp.flow`.
from .flow import FlowError, FlowParams, Trajectory, flow, flow_steps, sphericity, total_complexity  # noqa: E402
