"""vnc-warp: the VNC operator, VNC-Flow and the C-VAE of "VNC: A Scale-Space Foundation for Learnable
3D Surface Evolution", on NVIDIA Warp kernels with PyTorch interop."""

import logging

from ._version import __version__

# status messages of the library go to the "vnc_warp" logger; the application decides where (the CLI: stderr)
logging.getLogger(__name__).addHandler(logging.NullHandler())


def _source_checkout() -> None:
    """Map ``kernels/`` and ``training/`` of a source checkout to ``vnc_warp.kernels`` / ``vnc_warp.training``.

    pyproject installs the top-level folders under those names; run from a checkout (``python -m pytest``,
    ``python -m bench.vnc``), the folder ``vnc_warp/`` comes first on ``sys.path`` and has neither, so both are
    registered here from the folders beside it.
    """
    import importlib.util
    import os
    import sys

    here = os.path.dirname(os.path.abspath(__file__))
    for name in ("kernels", "training"):
        full = f"{__name__}.{name}"
        init = os.path.join(os.path.dirname(here), name, "__init__.py")
        if full in sys.modules or os.path.isdir(os.path.join(here, name)) or not os.path.isfile(init):
            continue
        spec = importlib.util.spec_from_file_location(full, init, submodule_search_locations=[os.path.dirname(init)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[full] = module
        spec.loader.exec_module(module)
        globals()[name] = module


_source_checkout()

from .mesh import EdgeTopology, Mesh, MeshError, MeshInput, from_arrays, load_mesh, mesh_input
from .tuning import Tuning
from ._engine import Engine, engine
from .operators import DegenerateResultWarning, edge_fields, integrated_mean_curvature, vnc_hard, vnc_soft
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
from .trajectory import TrajectoryError  # noqa: E402
