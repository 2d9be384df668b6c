"""VNC-Flow (paper Sec. 3.2, Algorithm 1): spacetime-balanced curvature flow sampling.

A detailed mesh goes in; a :class:`Trajectory` of ``stages + 1`` meshes and their normalized times
``t`` (Eq. 7) comes out, from the remeshed input (``t = 1``) to a near-sphere.

* **Flow step**, Eq. (5): ``v_k <- v_k - lambda (H_soft(v_k, tau_k) - H_ref) n_soft(v_k, tau_k)`` with
  ``H_ref`` the vertex mean of ``H_soft`` at the current iterate (the scale-stable global reference: the
  mean barely depends on scale, Fig. 6, and taking it at the current state keeps the flow from drifting
  inward or outward), added in a fixed order (:func:`reference_mean`) so that a run repeats bit for bit.
* **Step size rule**: at the first iteration of each stage ``lambda = eta * mean_edge_length / q90(|H - H_ref|)``
  (the 90th-percentile vertex moves ``eta`` mean edge lengths), capped at ``max_lambda`` mean edge lengths for
  stability, then held for the stage so moves shrink as the surface converges (``step_growth`` > 1 multiplies it
  after each run of steps that lowered ``S``, up to the uncapped rule, until the stage first backtracks; off by
  default); every move is clamped to ``eta`` times the vertex's own mean incident edge length. The rule is
  unit-free. **Why late stages stalled**: near a sphere ``q90`` is ~0.003, so the rule asks for 80-120 edge lengths
  and ``lambda`` sits at the cap; VNC-soft's ``H`` is proportional to the edge length, so a step moved the median
  vertex by ~0.008 of an edge (none at the clamp; nefertiti stage 30 at 6,000 and 24,000 faces, CPU), and the
  iterations a stage needs grow with the face count: 47 at stage 31 at 6,000 faces, the full ``max_iters`` = 300
  and the fallbacks at 50,000 (H200, 25fa345). Four times the cap lowered ``S`` 2.8 times as fast per step at
  24,000 faces but climbed at 6,000; growing the step where it holds (``step_growth``) cost more level-set remeshes
  within stages at full size than it saved (see :class:`FlowParams`), so neither is on by default. A stage that
  clearly cannot reach its window in the iterations left (twice over, at the rate of its last ``2 eval_max``
  iterations) goes to the fallbacks at once (``early_fallback``; said in its ``exception``). **Descent**: a run of steps
  that takes ``S`` more than ``_RISE`` (5 %) above its segment's start is not a descent step of Eq. (5): the
  stage goes back to its best state and halves the step (``lambda`` and every move clamp), a backtracking line
  search on ``S`` (within 5 % it goes on: a remeshed state is re-smoothed first, and ``S`` moves by a few
  percent between nearby states). Without it, on scorpion at 3,000 faces (limbs 1-2 edges thick) ``S`` rose
  from 1.0 to 3.7 ``S_init`` within stage 1 and the state no longer remeshed. (Adaptive scales only: the
  fixed-scale ablations of Fig. 7 keep the plain step.) The rise must also exceed 5 % of ``S_init``: near a
  sphere ``S`` is a few percent of ``S_init`` and noise of 1 % of an edge length moves it by half of itself, so a
  test against ``S`` alone halved the step of every late stage until it stalled. A run that climbs more than the
  stage's tolerance above its best ``S`` after ``S`` fell below the segment's start has passed the minimum of
  Eq. (5) at this step and is backtracked too: on hammer.obj at 12,000 faces (CPU, stage 16) ``S`` fell from t 0.559
  to 0.506 in 17 steps and then climbed to 0.67 over 100 steps at full step, where half the step reached 0.504 and a
  quarter 0.5005 (the stage took 255 iterations and a remesh, now 85).
* **Sub-stages**: the flow spends at most ``substage_budget`` (1/32 of ``S_init``) between two remeshes; a
  stage with a larger budget (N < 32) is flowed as that many sub-stages, each remeshed and given its adaptive
  scales, and records the last (its record lists them in ``substages``), so a trajectory of N = 8 holds states of
  the flow that N = 32 makes.
* **Spatial balance**, Eq. (6): per-vertex adaptive scales ``tau_k`` from the stage's VNC-Scale curves
  with ``phi = phi_fraction * mean_k s(v_k)``; recomputed at the start of every stage. **Thin parts** (see
  :data:`THIN_PARTS`): where the part around a vertex is a tube (shape factor ``rho`` = thickness along the
  inward normal times the mean curvature at the largest scale: 1 on a tube, 2 on a ball) the part-scale excess
  of curvature ``max(H(v_k, tau_max) - mean H(tau_max), 0)`` is turned around in Eq. (5), so the part fattens
  toward the shape's mean curvature and merges with its neighbours instead of thinning into a thread; its
  details are still smoothed. Where the part is thinner than its curvature at ``tau_max`` says (``rho < 1``: a
  neck between a limb and the body, whose ``tau_max`` also sees the body), its curvature at its own scale
  ``tau_k`` counts as part-scale (up to that of a tube as thick as the neck, and at most twice its curvature at
  ``tau_max``), and its excess takes off at most the inward part of the deviation, so the neck stops thinning
  while the limb fattens, instead of thinning into a stalk. The correction fades out between ``rho = tube_rho``
  and ``ball_rho``; balls, tips, flat and concave regions follow Eq. (5) as written. It is refreshed at every
  evaluation of ``S``.
* **Temporal balance**: ``S_init = sum_k s(v_k | M0)``; stage ``i`` ends at ``t_i = S_cur / S_init`` (Eq. 7)
  within ``tolerance`` of its equidistant target ``1 - i/N``. The stage controller plans the steps to the
  next evaluation of ``S`` from the decay rate observed so far and, when a run of steps overshoots the
  target, searches the chord between the last state above the window and the state below it (secant steps
  on the fraction of the chord) until ``t`` lands in the window (status ``budget``: only a stage whose ``t`` lies in
  its window has it; where the search closes on a jump of ``S``, the chord is scanned at ``_CHORD_SCAN`` evenly
  spaced fractions for a state in the window). Where no state on the chord lands in the window (``S`` jumps along
  it: on the H200, brucewick.obj's stage 29 of 32 from t 0.117 to 0.068 at one point of the chord, around its window
  0.094 +- 0.005, where a thorn formed; it recorded the nearest trial, t 0.117, as ``budget``), the stage goes back
  to its best state above the window and halves the step, as after a rise (see **Descent**; the record's
  ``chord_misses`` counts the chords searched in vain), at most ``_CHORD_RETRIES`` times and within ``max_iters``;
  a stage that still misses (or a baseline, which has no step to halve) ends at its best state above the window
  with status ``missed``, the chords in ``exception``, and goes to the fallbacks below as a stage short of its window
  does (``smoothed`` or ``blended`` where one lands it). Exceptions, recorded per stage as
  ``status`` and ``exception``: the **last stage** (target ``t = 0``, below the VNC-AUC of any meshed
  sphere) runs until ``S`` stops decreasing by 0.1 % over ``patience`` evaluations (status ``final``), its states
  scaled back to the volume it started with after each run of steps (``S`` at fixed scales falls as a shape shrinks);
  a stage whose **remesh changed the topology** (Euler characteristic, components: a handle closes, a part
  merges) and thereby already took ``S`` below its window records the remeshed state with no flow step
  (status ``remesh``); a stage that stops improving before its target ends ``converged`` with the ``t`` it
  reached; ``max_iters`` likewise, unless the **smoothing fallback** takes it on (every stage but the last):
  where Eq. (5) stops lowering ``S`` short of the window (it stands still or climbs ``S`` on a fattened dumbbell
  whose neck became a waist),
  backward-Euler mean-curvature steps from the best state, each kept only while it lowers ``S`` (where none does:
  the same with Eq. (5)'s mean, speed ``H - H_ref``, which does not shrink the shape into a needle; then both at four
  times the step, ``_FALLBACK_DT`` = 1 to 1024 squared edge lengths), and the last searched back on its chord, land it
  (status ``smoothed``, the steps, their kind and ``dt`` in ``exception``); before, such a
  stage recorded the previous state, and every later stage repeated it. Where the smoothing fallback too ends
  short of the window (a state where no curvature step lowers ``S``: on the H200 hammer.obj from stage 22, a
  ball-headed club whose handle keeps its length, since the thin-part rule stops it thinning and nothing shortens
  it; mushroom.obj from stage 28; boot.obj at stages 7-10 after a genus change), the **blend fallback** takes the
  best state toward its own equal-volume moment ellipsoid (same centroid and principal axes, semi-axes from the
  solid's second moments), the shape the last stage becomes (``bench/last_stage.py``,
  ``docs/results/last_stage_oracles``): the zero level set of ``(1 - a) f + a g``, ``f`` the state's signed
  distance (sampled once on the remesher's grid) and ``g`` the ellipsoid's, made by the remesher's level-set path
  and scaled to the state's volume (where even ``a = 1`` leaves the stage above its window, the same toward the
  sphere of the state's volume: a long-handled club's own ellipsoid is a cigar), with ``a`` in (0, 1] searched
  (Illinois secant steps, at most
  ``_BLEND_TRIALS``, ``S`` at the trajectory's scales) until ``t`` lands in the window (status ``blended``;
  ``a`` and the trials in ``exception`` and the record's ``blend``). Sec. 3.2 asks for a smooth abstraction
  ending near a sphere; as ``a`` grows a handle retracts into the head instead of thinning. The next stage tries
  Eq. (5) first again; if its first ``_EARLY_STALE`` evaluations make no progress it goes to the blend at once,
  without ``max_iters`` and the smoothing fallback. A stalled stage is remeshed from its best
  state and goes on (at most ``stall_remeshes`` times), at half the step if ``S`` never fell below the stage's
  start; on a shape with a handle whose ``S`` never fell, from its current state instead: a handle narrowing
  raises ``S`` (on a torus the thin-part rule fattens the tube and closes the hole), and only a remesh where the
  flow went closes it.
  A stage whose remesh, between stages or within, changed the topology records it in ``exception``; its
  ``t`` may lie above its window, even above 1 (a torus: 1.58 at the stage that closed its hole). A stage
  that cannot go on keeps its best state, also one from before a remesh within it; a stage whose best ``S``
  is still above the previous stage's (a near-sphere whose remesh raised ``S`` by more than the last stage
  can win back) keeps the previous state and ``t`` (status ``held``, the reason in ``exception``), except
  on a shape with a handle (Euler characteristic below 2), whose ``S`` must rise until the hole closes.
* **Bridge** (``bridge``): a remesh, between stages or within one, that takes ``t`` from a state ``P`` in or above
  stage ``i``'s window to a state ``Q`` below it (boot's eyelets closing in one level-set remesh) fills the stages
  whose windows lie between them with states on the path from ``P`` to ``Q``: the zero level set of
  ``(1 - a) f_P + a f_Q`` (signed distances on one grid, :class:`vnc_warp.remesh._SurfaceBlend`), ``a`` searched
  per stage (status ``bridged``, ``a`` and the trials in the record's ``bridge``); the flow goes on from ``Q``. A
  genus change along the path that makes ``t`` jump across a window is that stage's exception (status
  ``bridge jump``: the first state past the jump); the stages before and after it are normal. Where ``t`` jumps at
  ``a = 0+`` (``P``'s own level set is ``Q``: its parts met) the bridge is retried from the stage before ``P``,
  and failing that the stage records ``Q`` as before, with the reason (see :func:`_bridge`,
  ``docs/flow_balance.md``).
* **Topology regularization**: :func:`vnc_warp.remesh.sdf_remesh` before stage 0 and between stages, one
  remesher for the whole trajectory, kept on the device; its report (path, Euler characteristic, components
  dropped, repairs, seconds per part) is the stage record's ``remesh``. **Parts that meet**: at every evaluation
  of ``S`` above the stage's window the state is checked for parts inside other parts (the remesher's rule: more
  than 0.3 % of the vertices a fiftieth of a grid cell out along their normal lie inside the shape); such a state
  (two legs fattened into each other, a hole's rim meeting itself, a sheet folded over) is no surface, and the
  flow would go on
  through the overlap and record it, which the 5th-percentile thickness then measures (two legs side by side,
  ``tests/capsules.py``, 2 stages at 3000 faces: 0.503 -> 0.034, 31 of 1500 vertices buried; on the H200,
  human_man's stage 17: 0.325 -> 0.024, its legs joined by the next stage's remesh into a handle). It is
  remeshed at once (its level set joins the parts where they overlap) and the stage goes on from there, in
  ``remeshes_within``; when the join already took ``t`` into or below the window the stage records it (status
  ``remesh``). At most ``stall_remeshes`` remeshes within a stage, of either kind. A run of steps that climbed (see
  **Descent**) is taken back at half the step before it is checked for parts that met, so a climb into a contact is
  not joined. A join that would take ``t`` below the window with the topology unchanged (Euler characteristic
  kept, no piece of more than ``_PART_AREA`` of the level set's area dropped) removes no handle or part but ``S`` the
  level set cannot hold (a fin thinner than the grid folded into the shape), which no bridge can spread over the
  stages it skips: the stage goes to the smoothing fallback from its best state before the contact instead, and
  takes the join (status ``remesh``) only where the smoothed state is no nearer the window than the join or its
  parts still meet (``deferred_join`` in the record); a smoothed state above the window goes on to the blend.

The scale range is fixed from ``M0`` for the whole trajectory so every ``S`` is measured the same way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
import time
import logging
import warnings
from dataclasses import dataclass

import numpy as np
import warp as wp

from vnc_warp.kernels import flow as _k
from vnc_warp.kernels import sdf as _ks

from ._device import get_device
from ._reduce import face_measures, vertex_normals
from ._engine import engine
from .mesh import Mesh, MeshError, framed_mesh, load_mesh
from .operators import vnc_soft
from .scale import adaptive_scale, default_scales, scale_curve, vnc_auc
from .trajectory import Trajectory, resume

__all__ = ["FlowParams", "Trajectory", "FlowError", "flow", "flow_steps", "reference_mean", "total_complexity",
           "sphericity", "relative_thickness", "thinnest_part"]

# An evaluation makes progress when S falls by more than this share below the stage's best so far.
_PROGRESS = 1.0e-3
# A run of steps that takes S more than this share above its segment's start is not a descent: it is backtracked.
_RISE = 0.05
# ... and more than this share of S_init: near a sphere S is a few percent of S_init and moves by tens of percent of
# itself under noise of 1 % of an edge length (fandisk at 3,000 faces, t = 0.063: 0.063 -> 0.100), so a rise
# measured against S alone halved the step of every late stage until it stalled (issue 21, H200 at c2eac1e)
_RISE_INIT = 0.05
# A run of steps that climbs more than this many stage tolerances above the stage's best S, after S fell below its
# segment's start, has passed the minimum of Eq. (5) at this step size: it is backtracked (issue 21, see _run_stage)
_CLIMB = 1.0
# A run of steps that overshoots the window and whose chord holds no state in it (S jumps along the chord: on the H200,
# brucewick.obj's stage 29 of 32, t 0.117 -> 0.068 at one point of the chord, around the window 0.094 +- 0.005, where
# a thorn formed) is backtracked at half the step, at most this many times per stage; then the stage ends above its
# window (status "missed") and goes to the fallbacks. Before, it recorded the chord's nearest trial as "budget".
_CHORD_RETRIES = 3
# ... after its secant search, a chord that holds no state in its window is scanned at this many evenly spaced
# fractions before it counts as a miss (see _search_chord)
_CHORD_SCAN = 16
# A stage where Eq. (5) stops lowering S short of its window (max_iters or converged: a dumbbell whose neck fattened
# into a waist, at t 0.75, 3000 faces: every run of steps from there raised S, whatever the step, the scales (phi 1/8
# to 1, tau_min, tau_max) or the thin-part rule; hammer, mushroom and nefertiti on the H200) went on
# recording the same state, stage after stage. Backward-Euler mean-curvature steps of this many squared mean edge
# lengths lower S there (the dumbbell: 0.763 -> 0.613 -> 0.543; 5 overshoots into a shrinking, pinching shape whose
# S climbs) ...
_FALLBACK_DT = 1.0
# ... and where such a step does not lower S, the same step with Eq. (5)'s mean (speed H - mean H: the shape is not
# shrunk), then both at this many times the step, up to _FALLBACK_DT_MAX. Plain mean curvature flow alone (before)
# shrank the hammer at 6,000 faces (stage 17, t 0.478) into a needle (across 1.78 -> 0.76 at dt 16) and raised S at
# every dt from 1 to 256 (bench/flow_stall.py), so stages 18-32 kept stage 17's state; with the mean, four steps (dt 1,
# 1, 256, 256) land stage 18 at t 0.4371 (target 0.4375; sphericity 0.254 -> 0.415). The dumbbell's waist needs the
# plain step: with only the mean (before its volume was scaled back) its stage 2 stalled at t 0.725 (target 0.5).
_FALLBACK_GROWTH = 4.0
_FALLBACK_DT_MAX = 1024.0
# ... at most this many evaluations of S per stage, each step kept only while it lowers S.
_FALLBACK_TRIES = 24
# A stage that Eq. (5) and the smoothing fallback leave above its window is blended toward its moment ellipsoid
# (_ellipsoid_blend): at most this many blends (values of a) per stage ...
_BLEND_TRIALS = 10
# ... and a stage that starts from a blended state and whose first this many evaluations make no progress goes to the
# blend at once, without max_iters and the smoothing fallback (hammer on the H200: each held stage took 300 iterations
# and ~42 evaluations, 2.5 s)
_EARLY_STALE = 3
# A stage goes to its fallbacks early (FlowParams.early_fallback) when Eq. (5), at its recent rate, would need more than
# this many times the iterations left: a fallback costs ~10 evaluations of S and its state's next remesh raised t by
# 0.04-0.17 (hammer and mushroom at 6,000 faces), so only a clear shortfall is cut (mushroom at 6,000 faces: a margin
# of 1 cut stages 24 and 26 at 321 and 256 iterations needed for 245 and 234 left, where the code of b0571a3 landed
# every stage with Eq. (5), 132 iterations at most)
_CUT_MARGIN = 2.0
# ... blending toward the moment ellipsoid, then toward the sphere of its volume (see _EllipsoidBlend's roundness)
_BLEND_ROUNDNESS = (0.0, 1.0)
# A remesh that takes t below a stage's window is bridged (_bridge) on a grid this many times finer than the
# remesher's, so that the features the remesher's level set lost (boot's eyelets) are on the path at a = 0 ...
_BRIDGE_REFINE = 2.0
# ... with at most this many blends (values of a) per bridged stage, and a jump across a window located to this share
# of the path
_BRIDGE_TRIALS = 8
_BRIDGE_GAP = 0.01
# A level-set remesh that drops pieces of less than this share of its level set's area dropped no part of the shape:
# they are fragments of a fin or sheet thinner than the grid (fandisk's stage 23 at 12,946 faces, CPU: 2 pieces,
# 0.008 %), as the level set's tears are (docs/flow_balance.md, "Sheets thinner than the grid"); FAUST 025's forearm,
# a part that went, was 4.8 %
_PART_AREA = 0.005

# The thin-part rule's neck term (THIN_PARTS, "Necks"): where a vertex's curvature at its own scale is above its
# curvature at tau_max, and at most 1 / _NECK_BOUND times it, it counts as part-scale (up to that of a tube of the
# vertex's thickness). The necks of FAUST 025's arms read 1.2-1.4 (rho 0.3-0.75); the toe remnants of its stages 28-30
# read 2.2-15 (rho 0.01-0.45, thinner than 3 edges): unbounded and turned around in full, the term fattened them, and
# stage 30 from stage 29's state took 300 iterations and the smoothing fallback (23 with the rule before necks)
_NECK_BOUND = 0.5

THIN_PARTS = """Why limbs became threads, and the thin-part rule that makes them merge instead.

Measured on human_man (5000 faces, stage 0, 16 scales; docs/flow_balance.md has the commands): on the arms
``H - H_ref`` is +0.064 at the smallest scale and still +0.058 at the largest (0.65 m, about an arm's length),
on the torso -0.041 and -0.040. A thin tube has a large normalized H at every scale below its length, so
Eq. (5) moves its surface inward at every scale; the adaptive scales of Eq. (6) hardly differ there (median
tau 0.35 on the arms, 0.32 on the torso), so the scale rule neither causes nor prevents it, and the step clamp
only sets the pace (31 % of arm vertices at it; one step moved the arms inward by 0.14 mean edge lengths and
the torso outward by as much). Inward motion raises a tube's curvature (its cross-section's radius shrinks):
on a part, Eq. (5) climbs ``|H - H_ref|`` instead of descending it. The total VNC-AUC rose 15 % in the first 10
steps (arms +7 %, legs +5 %), the arms were threads after 23 steps, and the next SDF-remesh cut them off (t
0.72 -> 0.39 in one remesh; the base code on the full human_man: the 5th-percentile thickness ratio 0.76 at
stage 1). Capping the inward motion per stage instead (tried: 7.5 % of the thickness) stops the threads but
not the ascent: the stage budgets of Eq. (7) are then met only by the torso inflating into an egg that
swallows the limbs within two stages.

Sec. 3.2 states what the flow is for, "minimizing |H_soft - H_ref| -> 0", and introduces spatial balance
against exactly this failure, "flat regions may degenerate into singularities long before complex wrinkles
are resolved". The rule splits the deviation of Eq. (5) at a vertex into its part-scale share, the excess of
its curvature at the largest scale over the mean there, and the rest (detail). Where the part is a tube, moving
along the part-scale excess raises it, so that share is turned around: the part fattens toward the shape's
mean curvature while its details are still smoothed by Eq. (5). A tube is told from a ball or a tip by its
shape factor ``rho``, the thickness along the inward normal times the mean curvature at the largest scale
(VNC-soft's H is ``L / (2 sqrt 3)`` times the mean curvature on a regular tessellation of edge ``L``): 1 on a
tube (thickness 2r, curvature 1/2r), 2 on a ball, more at a tip; shrinking a ball or a tip lowers the total
VNC-AUC (its vertices go with its area), thinning a tube does not (its VNC-AUC is about its length over L
whatever its radius). The correction fades out between ``tube_rho`` and ``ball_rho`` and never touches
concave regions or parts flatter than the mean (a plate's faces still move apart, concavities still fill).
With it the total VNC-AUC falls from the first step, every stage meets its budget in a few steps, and limbs
shorten and fatten until they merge with the body and each other: the compact abstraction of Fig. 9a.

Necks (issue 21 item 3). The part-scale share is read at tau_max, and at a neck between a limb and the body
tau_max also sees the body: on FAUST 025 (6,000 faces, N = 32, code of 36d1669) the right arm fattened into a
ball while its shoulder thinned into a stalk (thinnest part 0.152 -> 0.044 over stages 11-16, relative to the
radius of the sphere of equal area) that the stage-17 remesh cut (the hand dropped, t 0.501 -> 0.409 against a
target of 0.469). On the shoulder vertices at stage 10 (50 vertices thinner than 0.75x the arm): rho 0.53 (the
arm 1.38), detail share ``H(tau_k) - H(tau_max)`` +0.014, part-scale excess +0.0075, so the deviation after the
turn-around stayed +0.0044 and 66 % of them moved inward (0.025 edge lengths per step, none at the clamp) while
the arm moved outward (-0.078); at stage 12 +0.0062, 77 % inward. The detail share of a neck is not detail: a
neck thinning raises its curvature at its own scale as a tube's thinning raises it at every scale. ``rho`` says
how much of it is the part's: a tube as thick as the part is at ``v_k`` has the curvature ``H(tau_max) / rho``
(``edge / (2 sqrt 3 thickness)``). So where ``H(tau_max) < H(tau_k) <= 2 H(tau_max)`` (``_NECK_BOUND``) the rule
takes ``min(H(tau_k), H(tau_max) / rho)`` as the part-scale curvature, and its turned-around excess takes off
at most the inward part of the deviation (kernels/flow.py, ``part_excess``, ``balanced_step``): on the stage-10
and stage-12 shoulders 4 % and 0 % of the vertices then move inward. A straight tube, a bump on one (``rho >=
1``), a dent, a ball, a tip, a flat or concave region keep the rule as before, and so does a thread or a thorn
whose curvature at its own scale is more than twice its curvature at tau_max (a toe's remnant near the end of
FAUST 025's flow: it is detail, and Eq. (5) shortens it). Turning the neck's excess around in full (pushing it
out) fattened such remnants too and stalled FAUST 025's stages 30-31 (300 iterations each, then the smoothing
fallback); bounding the curvature alone still took stage 30 175 iterations and the fallback; the rule adopted took
43 (23 with the rule before). FAUST 025's arms then shorten into knobs and merge as human_man's do
(docs/flow_balance.md).
"""


log = logging.getLogger(__name__)


class FlowError(RuntimeError):
    """VNC-Flow produced an invalid state (a bug, never recorded) or cannot resume."""


@dataclass
class FlowParams:
    """Parameters of :func:`flow` (all unit-free; scales come from the mesh).

    Attributes:
        stages: number of stages N of Algorithm 1.
        faces: face count of every remeshed state; None keeps the input's.
        num_scales: scales of the VNC-Scale curves (geometric, :func:`vnc_warp.default_scales`).
        kappa: VNC-soft cut-off ratio.
        step_fraction: eta of the step size rule (fraction of the mean edge length per iteration).
        max_lambda: stability cap on lambda, in mean edge lengths per radian of curvature deviation. The
            explicit step diverges above about 12-16 (measured on Spot with the default scales); 6 keeps a
            factor of two. It is where a stage starts: see ``step_growth``.
        step_growth: after each run of steps that lowered ``S`` by more than 0.1 %, ``lambda`` is multiplied by this,
            up to the step size rule's own value ``eta / q90`` (no ``max_lambda`` cap; not in the last stage), until
            the stage first backtracks (a run of steps that raised ``S`` is taken back at half the step, see the module
            docstring);
            1 (the default) keeps ``lambda`` fixed for the stage. Meant for late stages: near a sphere ``q90`` is
            small, ``lambda`` sits at the cap, and since VNC-soft's ``H`` scales with the edge length, each step moves
            a vertex by ``max_lambda`` edge lengths times ``H``, about one hundredth of an edge; at 50k faces the
            stages took the full ``max_iters`` (issue 21, H200 at 25fa345). Off by default: on an H200 at 0f6a070
            (bridge on), growth 2 against 1 gave max |t_i - (1 - i/N)| 0.027 against 0.009 on FAUST 025 and 0.005 on
            human_man either way (the meshes tuned on), and on the held-out hammer, koala and nefertiti 0.046 / 0.042
            / 0.005 against 0.005 / 0.005 / 0.013, with more level-set remeshes within stages (hammer 17 against
            10), in 32.0 / 29.0 / 18.2 s against 26.6 / 19.0 / 16.1 s.
        phi_fraction: Eq. (6) budget as a fraction of the stage's mean per-vertex VNC-AUC.
        tube_rho: where the shape factor ``rho`` (thickness along the inward normal times the mean curvature
            at the largest scale: 1 on a tube, 2 on a ball) is at most this, the part-scale excess of curvature
            is turned around in Eq. (5) (see :data:`THIN_PARTS`) ...
        ball_rho: ... fading out up to this ``rho``; ``tube_rho = ball_rho = 0`` is Eq. (5) as written.
        tolerance: a stage ends when its ``t`` is within this of its target ``1 - i/N``.
        max_iters: iteration cap per stage (per sub-stage, see ``substage_budget``).
        substage_budget: the largest share of ``S_init`` the flow spends between two remeshes. A stage whose
            budget ``1/N`` is larger (N < 32 by default) is flowed in ``ceil(substage_budget^-1 / N)`` equal
            sub-stages, each remeshed and given new adaptive scales (Eq. 6) as a stage is, and only its last is
            recorded (adaptive VNC-Flow; the Fig. 7 ablations and baselines keep one flow per stage): the flow
            between remeshes, and so the trajectory, is the same whatever N (before, at N = 8 a body's stage ran
            out of iterations 0.1-0.2 short of its target and Spot's ears thinned to a 0.06 thickness ratio within
            one long stage; H200, c2eac1e).
        stall_remeshes: a stage that stalls short of its target (``patience`` evaluations without progress)
            is remeshed from its best state and goes on, at most this many times (the same topology
            regularization as between stages; never in the last stage, whose target is out of reach).
        eval_every: evaluate ``S_cur`` at least this many iterations apart.
        eval_max: at most this many iterations apart. In between, the next evaluation is placed where the
            decay rate observed so far reaches the stage's target (the 16-scale evaluation of ``S`` costs
            several flow steps; an overshoot is searched back on the chord).
        patience: evaluations without a 0.1 % decrease of ``S_cur`` before a stage counts as converged.
        remesh: SDF-remesh before stage 0 and between stages.
        resolution: marching-cubes grid resolution of the remesher (None: automatic).
        allow_changes: accept a first remesh that drops components or loses thin parts (see
            :func:`vnc_warp.sdf_remesh`); later remeshes are part of the flow and only recorded.
        scale_mode: "adaptive" (Eq. 6), "small" (every vertex at tau_min) or "large" (tau_max): Fig. 7 (c, d).
        method: "vnc" (Eq. 5), "mcf_explicit" or "mcf_implicit" (cotangent-Laplacian mean curvature flow,
            Fig. 7 (e, f)); the baselines use the same stages and records, with ``mcf_dt`` in units of the
            squared mean edge length.
        mcf_dt: time step of the MCF baselines (None: 0.05 explicit, inside its stability limit of about 1/6,
            and 5.0 implicit).
        smoothing_fallback: a stage that Eq. (5) leaves short of its window is taken on by implicit smoothing
            steps (see the module docstring; False: an ablation).
        blend_fallback: ... and where those too end short, by the blend toward the moment ellipsoid.
        early_fallback: a stage whose step can grow no further (``step_growth``) and whose best ``S``, at the rate it
            fell over the last ``2 eval_max`` iterations (since its last backtrack), would need more than twice the
            iterations left before ``max_iters`` to reach the window goes to the fallbacks at once (its ``exception``
            says so, with the iterations it would have needed) instead of
            after ``max_iters`` and the stall remeshes on the way (False: it runs them out, as before).
        bridge: a remesh (between stages or within one) that takes ``t`` below the stage's window is bridged: the
            stages whose targets it skipped are filled with states on the level-set path from the state before the
            remesh to the state after it (see the module docstring; False: today's behaviour before the bridge, the
            remeshed state recorded and the skipped stages held). Default True.
    """

    stages: int = 32
    faces: int | None = None
    num_scales: int = 16
    kappa: float = 6.0
    step_fraction: float = 0.25
    max_lambda: float = 6.0
    step_growth: float = 1.0
    early_fallback: bool = True
    phi_fraction: float = 0.5
    tube_rho: float = 1.2
    ball_rho: float = 1.8
    tolerance: float = 0.005
    max_iters: int = 300
    substage_budget: float = 1.0 / 32.0
    stall_remeshes: int = 4
    eval_every: int = 1
    eval_max: int = 16
    patience: int = 8
    remesh: bool = True
    resolution: int | None = None
    allow_changes: bool = False
    scale_mode: str = "adaptive"
    method: str = "vnc"
    mcf_dt: float | None = None
    smoothing_fallback: bool = True
    blend_fallback: bool = True
    bridge: bool = True

    def __post_init__(self):
        if self.stages < 1:
            raise ValueError(f"stages must be >= 1, got {self.stages}")
        if not 0.0 < self.substage_budget <= 1.0:
            raise ValueError(f"substage_budget must be in (0, 1], got {self.substage_budget}")
        if self.scale_mode not in ("adaptive", "small", "large"):
            raise ValueError(f"scale_mode must be adaptive, small or large, got {self.scale_mode!r}")
        if self.method not in ("vnc", "mcf_explicit", "mcf_implicit"):
            raise ValueError(f"method must be vnc, mcf_explicit or mcf_implicit, got {self.method!r}")
        if not self.step_growth >= 1.0:
            raise ValueError(f"step_growth must be >= 1, got {self.step_growth}")
        for name in ("step_fraction", "phi_fraction", "kappa", "tolerance"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive")
        if not 0.0 <= self.tube_rho <= self.ball_rho:
            raise ValueError(f"need 0 <= tube_rho <= ball_rho, got {self.tube_rho} and {self.ball_rho}")
        if self.stall_remeshes < 0:
            raise ValueError(f"stall_remeshes must be >= 0, got {self.stall_remeshes}")
        if self.max_iters < 1 or self.eval_every < 1 or self.patience < 1 or self.eval_max < self.eval_every:
            raise ValueError("max_iters, eval_every and patience must be >= 1, and eval_max >= eval_every")


def _euler(mesh: Mesh) -> int:
    """Euler characteristic V - E + F (2 for a sphere, 0 for a torus): remeshing may close a handle."""
    return int(mesh.num_vertices - mesh.topology.edges.shape[0] + mesh.num_faces)


def sphericity(mesh: Mesh) -> float:
    """Isoperimetric quotient ``36 pi V^2 / A^3``: 1 for a sphere, smaller for anything else."""
    return float(36.0 * np.pi * mesh.volume() ** 2 / mesh.area() ** 3)


def _device_sum(values: wp.array) -> float:
    """``sum_k values[k]`` in float64, added in a fixed order (as :func:`reference_mean`), so that every decision
    the stage controller takes on ``S`` repeats bit for bit on any device."""
    partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=values.device)
    wp.launch(_k.strided_sums, dim=partial.shape[0], inputs=[values], outputs=[partial], device=values.device)
    return float(np.sum(partial.numpy(), dtype=np.float64))


def total_complexity(mesh: Mesh, taus, *, kappa: float = 6.0, positions: wp.array | None = None, device=None) -> float:
    """``S = sum_k s(v_k)``: the total VNC-AUC (Eq. 4 at tau_max) of a mesh, the numerator of Eq. (7)."""
    curve = scale_curve(mesh, taus, "soft", kappa=kappa, device=device, positions=positions)
    return _device_sum(vnc_auc(curve))


class _Surface:
    """A closed surface's positions and corners on one device, with its ``wp.Mesh`` for ray queries."""

    def __init__(self, x: wp.array, tri: wp.array):
        self.x, self.tri = x, tri
        self.mesh = wp.Mesh(points=x, indices=tri)

    @classmethod
    def of(cls, mesh: Mesh, device, positions: wp.array | None = None) -> _Surface:
        x = wp.clone(positions) if positions is not None else wp.array(mesh.local_vertices, dtype=wp.vec3,
                                                                         device=device)
        return cls(x, wp.array(mesh.faces.reshape(-1), dtype=wp.int32, device=device))

    def measures(self) -> tuple[float, float]:
        """Area and enclosed volume (float64 sums on the device)."""
        area, volume, _, _ = face_measures(self.x, self.tri)
        return area, volume

    def vertex_normals(self) -> wp.array:
        return vertex_normals(self.x, self.tri)

    def span(self) -> float:
        from .remesh import _device_bounds

        lo, hi = _device_bounds(self.x)
        return float(np.linalg.norm(hi - lo))

    def vertex_thickness(self, span: float | None = None) -> wp.array:
        """(V,) distance through the shape from each vertex along its inward normal (-1: no hit); ``span``:
        :meth:`span` of the current positions, if the caller already read it back."""
        out = wp.empty(self.x.shape[0], dtype=wp.float32, device=self.x.device)
        span = self.span() if span is None else span
        wp.launch(_ks.inward_thickness, dim=self.x.shape[0],
                  inputs=[self.mesh.id, self.x, self.vertex_normals(), 1e-5 * span, 2.0 * span], outputs=[out],
                  device=self.x.device)
        return out

    def relative_thickness(self, area: float, percentile: float = 5.0, samples: int = 4096,
                           span: float | None = None) -> float:
        """:func:`relative_thickness` of this state of area ``area``."""
        from .sdf import inward_distances

        hits = inward_distances(self.mesh, self.x, self.tri, samples, span=self.span() if span is None else span)
        return float(np.percentile(hits, percentile) / np.sqrt(area / (4.0 * np.pi)))

    def thinnest_part(self, area: float, edges: np.ndarray, span: float | None = None) -> float:
        """:func:`thinnest_part` of this state of area ``area`` and edges ``edges``."""
        return _ring_median_min(self.vertex_thickness(span).numpy(), edges) / float(np.sqrt(area / (4.0 * np.pi)))


def relative_thickness(mesh: Mesh, *, percentile: float = 5.0, samples: int = 4096, device=None,
                       positions: wp.array | None = None) -> float:
    """How thin the thinnest parts of a closed surface are, relative to its size.

    The area-weighted ``percentile`` of the distance through the shape along inward face normals
    (``samples`` rays from area-weighted random faces, fixed seed), divided by the radius of the sphere of
    equal area ``sqrt(A / 4 pi)``: about 2 for a sphere, 0.1 for a body with thin arms; a part thinning
    into a thread or a fin drives it down. VNC-Flow records it per stage.

    Args:
        mesh: a closed, outward-wound :class:`~vnc_warp.mesh.Mesh`.
        percentile: which percentile (0-100).
        samples: number of rays.
        device: Warp device.
        positions: (V,) vec3 positions overriding ``mesh.vertices``.

    Returns:
        The dimensionless relative thickness.
    """
    surface = _Surface.of(mesh, positions.device if positions is not None else get_device(device), positions)
    return surface.relative_thickness(surface.measures()[0], percentile, samples)


def _ring_median_min(thickness: np.ndarray, edges: np.ndarray) -> float:
    """``min_k median{thickness[j] : j = k or j adjacent to k}`` over the vertices whose ray hit (``> 0``); NaN when
    none did. The median over a vertex's 1-ring ignores a single short ray (a grazing hit near a tip or a crease)."""
    V = thickness.shape[0]
    th = np.where(thickness > 0, thickness.astype(np.float64), np.nan)
    a = np.concatenate([edges[:, 0], edges[:, 1], np.arange(V)])
    b = np.concatenate([edges[:, 1], edges[:, 0], np.arange(V)])
    order = np.argsort(a, kind="stable")
    a, b = a[order], b[order]
    count = np.bincount(a, minlength=V)
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    ring = np.full((V, int(count.max())), np.nan)
    ring[a, np.arange(a.shape[0]) - start[a]] = th[b]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a ring with no hit at all
        med = np.nanmedian(ring, axis=1)
    return float(np.nanmin(med)) if np.isfinite(med).any() else float("nan")


def thinnest_part(mesh: Mesh, *, device=None, positions: wp.array | None = None) -> float:
    """How thick the thinnest part of a closed surface is, relative to its size: a stalk, a thread or a fin of any
    area.

    Per vertex, the distance through the shape along its inward normal (the thickness the thin-part rule reads);
    its median over the vertex and its neighbours (so one grazing ray does not count); the smallest such median
    over the surface, divided by the radius of the sphere of equal area ``sqrt(A / 4 pi)``. Unlike
    :func:`relative_thickness` (an area-weighted percentile: a stalk that carries a hand carries too little area to
    move it) one ring of a few vertices is enough: a limb's neck thinning into a stalk drives it down. About 2 for
    a sphere. VNC-Flow records it per stage beside the 5th-percentile thickness (``thinnest``,
    ``thinnest_ratio``).

    Args:
        mesh: a closed, outward-wound :class:`~vnc_warp.mesh.Mesh`.
        device: Warp device.
        positions: (V,) vec3 positions overriding ``mesh.vertices``.

    Returns:
        The dimensionless thickness of the thinnest part (NaN if no inward ray hit).
    """
    surface = _Surface.of(mesh, positions.device if positions is not None else get_device(device), positions)
    return surface.thinnest_part(surface.measures()[0], mesh.topology.edges)


def _mesh_digest(mesh: Mesh) -> str:
    h = hashlib.sha256(np.ascontiguousarray(mesh.vertices).tobytes())
    h.update(np.ascontiguousarray(mesh.faces).tobytes())
    return h.hexdigest()[:16]


def _local_edge_length(mesh: Mesh) -> np.ndarray:
    """(V,) float32 mean length of each vertex's incident edges, in mesh units (float64 sums in edge order on the
    host, so every device clamps the moves of Eq. (5) alike)."""
    e = mesh.topology.edges
    v = mesh.local_vertices.astype(np.float64)
    length = np.linalg.norm(v[e[:, 1]] - v[e[:, 0]], axis=1)
    V = mesh.num_vertices
    total = np.bincount(e[:, 0], length, V) + np.bincount(e[:, 1], length, V)
    count = np.bincount(e[:, 0], minlength=V) + np.bincount(e[:, 1], minlength=V)
    return (total / np.maximum(count, 1)).astype(np.float32)


def reference_mean(H: wp.array, out: wp.array, *, partial: wp.array | None = None, tape: wp.Tape | None = None) -> None:
    """``out[0] = mean_k H[k]``, the global reference ``H_ref`` of Eq. (5), added in a fixed order.

    Float64 partial sums of a fixed stride (:data:`vnc_warp.kernels.flow.MEAN_PARTS`), then one thread adds them in
    order: unlike an atomic float sum (whose order follows thread timing on CUDA) the result is the same on every
    run and every device that computes the same ``H``, and within rounding of the float64 mean.

    Args:
        H: (V,) float32 values.
        out: (1,) float32, overwritten.
        partial: (MEAN_PARTS,) float64 scratch on ``H``'s device (allocated when None).
        tape: the ``wp.Tape`` being recorded: the adjoint ``H.grad += out.grad / V`` is recorded on it.
    """
    device = H.device
    V = H.shape[0]
    if partial is None:
        partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
    wp.launch(_k.strided_sums, dim=partial.shape[0], inputs=[H], outputs=[partial], device=device, record_tape=False)
    wp.launch(_k.ordered_mean, dim=1, inputs=[partial, wp.float64(1.0 / V)], outputs=[out], device=device,
              record_tape=False)
    if tape is not None:
        def backward():
            wp.launch(_k.mean_adjoint, dim=V, inputs=[out.grad, 1.0 / V], outputs=[H.grad], device=device,
                      record_tape=False)

        tape.record_func(backward=backward, arrays=[H, out])


def flow_steps(
    mesh: Mesh,
    positions: wp.array,
    tau,
    steps: int,
    *,
    lam: float,
    max_move,
    kappa: float = 6.0,
    tape: wp.Tape | None = None,
) -> list:
    """``steps`` iterations of Eq. (5) at fixed adjacency, each writing a new state: differentiable on a tape.

    Args:
        mesh: connectivity (positions come from ``positions``).
        positions: (V,) vec3 initial state; ``requires_grad=True`` to differentiate.
        tau: per-vertex scales (scalar or (V,)), held fixed.
        steps: number of iterations K.
        lam: step size lambda (mesh units, held fixed).
        max_move: per-vertex move clamp (scalar or (V,)).
        kappa: VNC-soft cut-off ratio.
        tape: the ``wp.Tape`` being recorded, if any.

    Returns:
        The K+1 states ``[x_0, ..., x_K]`` (``x_0`` is ``positions``).
    """
    from .operators import _per_point

    device = positions.device
    V = mesh.num_vertices
    tau_arr = _per_point(tau, V, device, "tau")
    mm = _per_point(max_move, V, device, "max_move")
    partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
    states = [positions]
    for _ in range(steps):
        x = states[-1]
        H, n = vnc_soft(mesh, tau_arr, kappa=kappa, positions=x, tape=tape)
        ref = wp.zeros(1, dtype=wp.float32, device=device, requires_grad=x.requires_grad)
        reference_mean(H, ref, partial=partial, tape=tape)
        out = wp.empty(V, dtype=wp.vec3, device=device, requires_grad=x.requires_grad)
        wp.launch(_k.flow_step, dim=V, inputs=[x, H, n, ref, float(lam), mm], outputs=[out], device=device)
        states.append(out)
    return states


class _Engine:
    """The VNC operator as one stage of VNC-Flow calls it: Eq. (3) at per-vertex scales for the step, and the
    VNC-Scale curves (Eq. 4) for ``S``, both at positions given on the device. It holds the mesh's
    :class:`~vnc_warp.Engine` for the stage: planned once, then replayed at every step's moving positions."""

    def __init__(self, mesh: Mesh, taus: np.ndarray, kappa: float, device):
        self.mesh, self.taus, self.kappa = mesh, taus, kappa
        self.vnc = engine(mesh, device)

    def soft(self, x: wp.array, tau: wp.array) -> tuple[wp.array, wp.array]:
        return self.vnc.vnc_soft(tau, kappa=self.kappa, positions=x)

    def curve(self, x: wp.array):
        return scale_curve(self.mesh, self.taus, "soft", kappa=self.kappa, positions=x)

    def complexity(self, x: wp.array) -> float:
        return _device_sum(vnc_auc(self.curve(x)))


def _quantile90(values: wp.array, ref: wp.array) -> float:
    """The 90th percentile of ``|values - ref[0]|`` to 1/1024 of their range, from a device histogram."""
    dev = values.device
    top = wp.zeros(1, dtype=wp.float32, device=dev)
    wp.launch(_k.max_deviation, dim=values.shape[0], inputs=[values, ref], outputs=[top], device=dev)
    counts = wp.zeros(1024, dtype=wp.int32, device=dev)
    wp.launch(_k.deviation_histogram, dim=values.shape[0], inputs=[values, ref, top], outputs=[counts], device=dev)
    c = np.cumsum(counts.numpy())
    return float(top.numpy()[0]) * (int(np.searchsorted(c, 0.9 * c[-1])) + 1) / counts.shape[0]


class _Stepper:
    """One stage's iteration: Eq. (5) (VNC) or a cotangent-Laplacian MCF baseline, on device positions ``x``."""

    def __init__(self, mesh: Mesh, taus: np.ndarray, p: FlowParams, device, positions: wp.array | None = None, *,
                 step_scale: float = 1.0):
        self.mesh, self.p, self.device = mesh, p, device
        self.step_scale = step_scale
        self.surface = _Surface.of(mesh, device, positions)
        self.x = self.surface.x
        self.x_next = wp.empty_like(self.x)
        self.ref = wp.zeros(1, dtype=wp.float32, device=device)
        self.engine = _Engine(mesh, taus, p.kappa, device)
        self.partial = wp.empty(_k.MEAN_PARTS, dtype=wp.float64, device=device)
        self.lam = None
        self.lam_rule = None
        self.backtracked = False
        self.S_start = None
        self.move_scale = 1.0
        V = mesh.num_vertices
        local = _local_edge_length(mesh)
        self.local = local
        self.edge = mesh.mean_edge_length
        if p.method == "vnc":
            curve = self.engine.curve(self.x)
            s = vnc_auc(curve)
            self.S_start = _device_sum(s)
            if p.scale_mode == "adaptive":
                self.tau = adaptive_scale(curve, taus, p.phi_fraction * self.S_start / V)
            else:
                t = taus[0] if p.scale_mode == "small" else taus[-1]
                self.tau = wp.full(V, np.float32(t), dtype=wp.float32, device=device)
            self.max_move = wp.array(p.step_fraction * local, dtype=wp.float32, device=device)
            self.part = wp.zeros(V, dtype=wp.vec4, device=device)
            self._thin_parts(curve)
        else:
            self._laplacian()

    def _thin_parts(self, curve) -> None:
        """The thin-part correction of the current state (:data:`THIN_PARTS`), from its scale curves: kept up
        to date at every evaluation of ``S``, since a part that fattens stops needing it."""
        p = self.p
        if p.ball_rho <= 0.0:
            return
        # the stepper's own surface, refitted at the current positions (a new wp.Mesh would rebuild its BVH at every
        # evaluation); its points are one of the two step buffers, so copying into it when it is the other one's
        # spare loses nothing: the next step overwrites the spare in full
        surface = self.surface
        if self.x.ptr != surface.x.ptr:
            wp.copy(surface.x, self.x)
        surface.mesh.refit()
        wp.launch(_k.thin_part_correction, dim=self.mesh.num_vertices,
                  inputs=[surface.vertex_thickness(), curve.H, curve.mean, curve.H.shape[0] - 1, float(self.edge),
                          float(p.tube_rho), float(p.ball_rho)],
                  outputs=[self.part], device=self.device)

    def _laplacian(self):
        import scipy.sparse as sp

        v = self.mesh.local_vertices.astype(np.float64)
        f = self.mesh.faces
        V = v.shape[0]
        rows, cols, vals = [], [], []
        area = np.zeros(V)
        for i in range(3):
            a, b, c = f[:, i], f[:, (i + 1) % 3], f[:, (i + 2) % 3]
            u, w = v[b] - v[a], v[c] - v[a]
            cot = (u * w).sum(1) / np.maximum(np.linalg.norm(np.cross(u, w), axis=1), 1e-30)
            rows += [b, c]
            cols += [c, b]
            vals += [0.5 * cot, 0.5 * cot]
        tri = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
        for i in range(3):
            np.add.at(area, f[:, i], tri / 3.0)
        W = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(V, V)).tocsr()
        self.L = W - sp.diags(np.asarray(W.sum(1)).ravel())
        self.M = sp.diags(area)
        default = 0.05 if self.p.method == "mcf_explicit" else 5.0
        self.dt = (self.p.mcf_dt or default) * self.edge**2
        if self.p.method == "mcf_implicit":
            from scipy.sparse.linalg import factorized

            self.solve = factorized((self.M - self.dt * self.L).tocsc())

    def step(self) -> None:
        p = self.p
        if p.method == "vnc":
            H, n = self.engine.soft(self.x, self.tau)
            reference_mean(H, self.ref, partial=self.partial)
            V = self.mesh.num_vertices
            if self.lam is None:
                q = _quantile90(H, self.ref)
                self.lam_rule = self.step_scale * (p.step_fraction / q if q > 0 else 0.0) * self.edge
                self.lam = min(self.lam_rule, self.step_scale * p.max_lambda * self.edge)
            wp.launch(_k.balanced_step, dim=V,
                      inputs=[self.x, H, n, self.ref, self.lam, self.max_move, self.part, _NECK_BOUND],
                      outputs=[self.x_next], device=self.device)
            self.x, self.x_next = self.x_next, self.x
            return
        v = self.x.numpy().astype(np.float64)
        if p.method == "mcf_explicit":
            v = v + self.dt * (self.L @ v) / self.M.diagonal()[:, None]
        else:
            v = np.stack([self.solve(self.M @ v[:, d]) for d in range(3)], axis=1)
        self.x = wp.array(v.astype(np.float32), dtype=wp.vec3, device=self.device)

    def backtrack(self, x: wp.array, part: wp.array) -> None:
        """Go back to the state ``x`` (with its thin-part correction ``part``) and halve the step: ``lambda`` and
        every vertex's move clamp, so that each move of Eq. (5) is half what it was."""
        wp.copy(self.x, x)
        wp.copy(self.part, part)
        self.backtracked = True
        self.move_scale *= 0.5
        self.lam *= 0.5
        self.max_move = wp.array(np.float32(self.p.step_fraction * self.move_scale) * self.local, dtype=wp.float32,
                                 device=self.device)

    def can_grow(self) -> bool:
        """Whether :meth:`grow` would still enlarge the step."""
        return (self.lam is not None and not self.backtracked and self.lam < self.lam_rule
                and self.p.step_growth > 1.0)

    def grow(self) -> bool:
        """After a run of steps that lowered ``S``: multiply ``lambda`` by ``step_growth``, up to the step size rule's
        own value (the 90th-percentile vertex moves ``eta`` mean edge lengths, without the ``max_lambda`` cap), and
        never again in a stage that backtracked. Returns whether it grew."""
        if not self.can_grow():
            return False
        self.lam = min(self.lam * self.p.step_growth, self.lam_rule)
        return True

    def volume(self) -> float:
        """The volume the current state encloses."""
        return float(face_measures(self.x, self.surface.tri)[1])

    def hold_volume(self, volume: float) -> None:
        """Scale the current state about its vertex centroid back to the enclosed ``volume``."""
        wp.copy(self.x, _scaled_to_volume(self.x, self.surface.tri, volume, self.device))

    def complexity(self) -> float:
        """``S`` of the current state (and, for Eq. (5), its thin-part correction refreshed from the same curves)."""
        if self.p.method != "vnc":
            return self.engine.complexity(self.x)
        curve = self.engine.curve(self.x)
        self._thin_parts(curve)
        return _device_sum(vnc_auc(curve))

    def current(self) -> Mesh:
        """The current state in absolute coordinates (the device positions are relative to ``mesh.origin``)."""
        # a copy: on the CPU device .numpy() is a view of the array, which later steps overwrite
        return framed_mesh(self.x.numpy().copy(), self.mesh.faces, self.mesh.topology, self.mesh.name,
                           self.mesh.origin)


def _as_saved(mesh: Mesh, origin: np.ndarray | None = None) -> Mesh:
    """The state as a resumed run reads it back: float32 vertices with no float64 history (the stage PLY holds
    float32), so that a run resumed from its files continues bit-identically to one never interrupted. With
    ``origin``, in the trajectory's frame: its :attr:`~vnc_warp.mesh.Mesh.local_vertices`, what the stages compute
    on, are taken relative to ``origin`` (float64), the same for a state just made and one read from disk."""
    from .mesh import EdgeTopology, _build_topology

    faces = np.ascontiguousarray(mesh.faces, dtype=np.int32)
    # the edges in the order load_mesh gives them (the remesher builds them on the device in another order, and
    # the order of the sums over edges shows in the last bits). Both take each interior edge's (a, b, c0, c1) from
    # its half-edge first in face order, so a closed surface's edges only need sorting by their endpoints: one sort
    # of E keys instead of _build_topology's pass over the faces (koala at 50k faces: 29 -> 2.4 ms per state)
    topo = mesh.topology
    if topo.boundary.shape[0] == 0 and topo.interior.shape[0] == topo.edges.shape[0] == 3 * faces.shape[0] // 2:
        key = topo.edges[:, 0].astype(np.int64) * mesh.num_vertices + topo.edges[:, 1]
        order = np.argsort(key)
        topology = EdgeTopology(topo.edges[order], topo.interior[order], topo.boundary)
    else:
        topology, _ = _build_topology(faces)
    return Mesh(np.ascontiguousarray(mesh.vertices, dtype=np.float32), faces, topology, mesh.name,
                origin=None if origin is None else np.asarray(origin, np.float64))


def _check_state(mesh: Mesh) -> str | None:
    from .remesh import surface_problems

    problems = surface_problems(mesh.vertices, mesh.faces)
    return "; ".join(problems) if problems else None


def _params_key(p: FlowParams) -> dict:
    return dataclasses.asdict(p)


def flow(
    mesh,
    stages: int = 32,
    faces: int | None = None,
    device=None,
    *,
    out_dir: str | os.PathLike | None = None,
    progress: bool = True,
    **params,
) -> Trajectory:
    """Run VNC-Flow (Algorithm 1) and return the trajectory; see the module docstring for the rules.

    Args:
        mesh: input mesh: a :class:`Mesh`, a ``trimesh.Trimesh``, a ``(V, F)`` pair (NumPy or torch) or a path;
            it must be watertight unless ``remesh`` is on (the SDF remesher closes holes with the winding-number
            sign). With ``remesh`` on, non-manifold edges and vertices, duplicate faces and several components are
            repaired by the first remesh, which says what it repaired (the ``vnc_warp`` logger) and records it
            (``info["repairs"]`` and stage 0's ``remesh`` record).
        stages: number of stages N.
        faces: face count of the remeshed states (None: the input's).
        device: Warp device.
        out_dir: write each stage as soon as it is finished (PLY + ``manifest.json``, :mod:`vnc_warp.trajectory`);
            if the folder already holds a run with the same input and parameters, resume after its last finished
            stage. The folder is checked before anything is computed.
        progress: show a progress bar (stage, iterations, t, seconds).
        **params: any other :class:`FlowParams` field.

    Remesh jumps and genus changes: a remesh that takes ``t`` below a stage's window is bridged (the skipped stages
    are states on the level-set path from the state before the remesh to the one after it, status ``bridged``); a
    genus change along that path that jumps across a window is recorded as that stage's exception (status
    ``bridge jump``), and a remesh whose path jumps at once keeps today's record (status ``remesh``, the reason in
    ``exception``). A genus change by a remesh that leaves ``t`` in or above the window is recorded in
    ``exception`` as before. See the module docstring.

    Returns:
        The :class:`Trajectory` (N+1 meshes unless a baseline collapsed first).

    Raises:
        MeshError: the input is not watertight and ``remesh=False``, or is otherwise invalid, or its first
            remesh would not be a faithful surface (pass ``allow_changes=True`` to accept it).
        FlowError: a VNC-Flow state failed validity (a bug).
        TrajectoryError: ``out_dir`` holds a different run, stage files it does not own, or damaged files.
        OSError: ``out_dir`` cannot be created or written to.
    """
    from .remesh import RemeshWarning, _Remesher

    p = FlowParams(stages=stages, faces=faces, **params)
    device = get_device(device)
    remesher = _Remesher(faces=p.faces, resolution=p.resolution, device=device, allow_changes=p.allow_changes,
                         warn=False) if p.remesh else None
    if remesher is not None:
        from .remesh import _read_source

        src = _read_source(mesh)
        name, digest = src.name, _digest_arrays(src.v, src.f)
    else:
        src = load_mesh(mesh)
        if not src.is_watertight:
            raise MeshError(f"{src.name}: not watertight ({src.topology.boundary.shape[0]} boundary edges); "
                            "VNC-Flow needs a closed surface: enable remesh (SDF remeshing closes it)")
        name, digest = src.name, _mesh_digest(src)
    info = {"params": _params_key(p), "source": name, "source_digest": digest, "version": _version(),
            "device": str(device)}
    traj = resume(out_dir, info) if out_dir is not None else None
    t_start = time.perf_counter()
    if traj is None:
        rec = {"index": 0, "t": 1.0, "file": "stage_000.ply", "iterations": 0, "status": "input"}
        if remesher is not None:
            m0, report = remesher(src)
            rec["remesh"] = report.to_dict()
            if report.grid_refined:
                log.info(f"VNC-Flow {name}: the first remesh {report.grid_refined}")
            if report.changes:
                message = f"VNC-Flow {name}: the first remesh " + "; ".join(report.changes)
                if report.lost_area or report.dropped_components or "topology changed" in message:
                    warnings.warn(message, RemeshWarning, stacklevel=2)
                else:
                    log.warning(message)
            info.update(repairs=report.repairs, remesh_spacing=report.spacing, remesh_changes=report.changes)
        else:
            m0 = src
        m0 = _as_saved(m0)
        taus = default_scales(m0, p.num_scales)
        S_init = total_complexity(m0, taus, kappa=p.kappa, device=device)
        if not S_init > 0:
            raise FlowError(f"{name}: total VNC-AUC is {S_init}; nothing to flow")
        info.update(taus=taus.tolist(), S_init=S_init, phi_stage=S_init / p.stages)
        rec.update(S=S_init, seconds=time.perf_counter() - t_start, **_facts(m0, device))
        traj = Trajectory([m0], np.array([1.0]), [rec], info)
        if out_dir is not None:
            traj.save(out_dir)
    # one frame for the whole trajectory: stage 0's centre, taken from its float32 vertices as stored (as
    # _as_saved(stage 0).origin is, without building its edges)
    v0 = np.ascontiguousarray(traj.meshes[0].vertices, dtype=np.float32)
    origin = 0.5 * (v0.min(0).astype(np.float64) + v0.max(0).astype(np.float64))
    if remesher is not None:
        remesher.adopt(_as_saved(traj.meshes[-1], origin), traj.info["remesh_spacing"], name)
    taus = np.asarray(traj.info["taus"])
    S_init = traj.info["S_init"]
    # sub-stages per stage (adaptive VNC-Flow only: the Fig. 7 ablations and baselines keep one flow per stage)
    adaptive = p.method == "vnc" and p.scale_mode == "adaptive"
    m = max(1, math.ceil(1.0 / (p.stages * p.substage_budget) - 1e-9)) if adaptive else 1
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=p.stages, initial=len(traj.meshes) - 1, desc=f"VNC-Flow {name}", unit="stage")
    try:
        # the bridged stages made and not yet recorded, and the state after the bridged remesh that the stage after
        # them flows from (see _bridge); a run resumed inside a bridge goes on from its last recorded state instead
        pending, after_bridge = [], None
        while len(traj.meshes) <= p.stages and traj.records[-1]["status"] != "collapsed":
            i = len(traj.meshes)
            t0 = time.perf_counter()
            # the state as stored, so that a resumed run goes on from exactly what an uninterrupted one does
            prev = traj.meshes[-1]
            if not np.array_equal(prev.origin, origin):  # read from disk: into the trajectory's frame
                prev = _as_saved(prev, origin)
            last = traj.records[-1]
            if pending:
                state, rec = pending.pop(0)
            else:
                subs, state = [], prev
                # the state before the stage's last remesh and its S: where a bridge starts
                before = (prev, None, last["S"], "the remesh between stages")
                for j in range(1, m + 1):
                    # sub-stage j of m (m = 1 unless a stage's budget exceeds substage_budget): remeshed, given its
                    # adaptive scales and flowed as a stage is, to 1 - ((i - 1) m + j) / (N m)
                    sub = {"index": i}
                    if after_bridge is not None and j == 1:
                        # the stages skipped by a remesh were bridged: on from the state that remesh made
                        cur, after_bridge = after_bridge, None
                        remesher.adopt(cur, traj.info["remesh_spacing"], name)
                        sub["from_bridge"] = True
                    elif remesher is not None and (i > 1 or j > 1):
                        before = (state, None, subs[-1]["S"] if subs else last["S"],
                                  "the remesh between sub-stages" if subs else "the remesh between stages")
                        cur, report = remesher(positions=wp.array(state.local_vertices, dtype=wp.vec3,
                                                                  device=device))
                        sub["remesh"] = report.to_dict()
                    else:
                        cur = state
                    state, _ = _run_stage(cur, i, taus, S_init, p, device, bar, sub, remesher,
                                          goal=((i - 1) * m + j) / (p.stages * m),
                                          previous=subs[-1] if subs else last)
                    before = sub.pop("before_remesh", before)
                    subs.append(sub)
                    if j < m:
                        state = _as_saved(state, origin)
                        if remesher is not None and sub.pop("kept", False):
                            remesher.adopt(state, traj.info["remesh_spacing"], name)
                rec = _merge_substages(subs)
                if (adaptive and remesher is not None and p.bridge and i < p.stages
                        and rec["S"] < S_init * (1.0 - i / p.stages - p.tolerance)
                        and before[2] >= S_init * (1.0 - i / p.stages - p.tolerance)):
                    q = _as_saved(state, origin)
                    bridged, why = _bridge(remesher, before, q, rec, i, taus, S_init, p, device)
                    if not bridged and before[3] == "the remesh between stages" and i >= 2:
                        # the previous state's own level set is the remeshed one (its parts met: a self-intersection
                        # the remesh joined): from the stage before it instead
                        earlier = _as_saved(traj.meshes[-2], origin)
                        bridged, _ = _bridge(remesher, (earlier, None, traj.records[-2]["S"],
                                                        f"the remesh of stage {i - 1}'s state (from stage {i - 2}'s)"),
                                             q, rec, i, taus, S_init, p, device)
                    if bridged:
                        if "deferred_join" in rec:
                            # the join was put off and taken after all (see _run_stage): the first bridged stage
                            # says so
                            bridged[0][1]["deferred_join"] = rec["deferred_join"]
                        (state, rec), pending, after_bridge = bridged[0], bridged[1:], q
                    else:
                        rec["exception"] = ((rec["exception"] + "; ") if rec.get("exception") else "") + why
            if adaptive and rec["S"] > last["S"] and _euler(prev) == 2 and "bridge" not in rec:
                # A stage that ends above the previous one's S did not descend: it keeps the previous state and t
                # (a shape with a handle is the exception: its S rises while the hole narrows until a remesh
                # closes it)
                rec["exception"] = ((rec["exception"] + "; ") if rec.get("exception") else "") + (
                    f"no descent: the best state reached t = {rec['t']:.4f}, above the previous stage's "
                    f"{last['t']:.4f}; keeping the previous state")
                rec.update(t=last["t"], S=last["S"], status="held", **_facts(prev, device))
                state = prev
            state = _as_saved(state, origin)
            if remesher is not None and "bridge" not in rec and (rec.pop("kept", False) or rec["status"] == "held"):
                # the remesher holds the last state it made; this stage recorded another: continue from it, as a
                # resumed run does
                remesher.adopt(state, traj.info["remesh_spacing"], name)
            rec.update(file=f"stage_{i:03d}.ply", seconds=time.perf_counter() - t0)
            rec["thickness_ratio"] = rec["thickness"] / last["thickness"] if last.get("thickness") else None
            rec["thinnest_ratio"] = rec["thinnest"] / last["thinnest"] if last.get("thinnest") else None
            traj.meshes.append(state)
            traj.records.append(rec)
            traj.t = np.append(traj.t, rec["t"])
            if rec.get("exception"):
                warnings.warn(f"VNC-Flow stage {i}: {rec['exception']} ({name})", stacklevel=2)
            if out_dir is not None:
                traj.save(out_dir)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(it=rec["iterations"], t=f"{rec['t']:.3f}", s=f"{rec['seconds']:.1f}")
    finally:
        if bar is not None:
            bar.close()
    problem = _check_state(traj.meshes[-1])
    if problem:
        raise FlowError(f"VNC-Flow stage {len(traj.meshes) - 1} produced an invalid surface ({problem}); this is "
                        "a bug, please report it")
    return traj


def _bridge(remesher, before: tuple, q: Mesh, rec: dict, i: int, taus, S_init: float, p: FlowParams, device
            ) -> tuple[list[tuple[Mesh, dict]], str | None]:
    """Fill the stages that a remesh skipped. ``before = (mesh, positions or None, S, which remesh)`` is the state ``P``
    before the remesh (in or above stage ``i``'s window), ``q`` the stage's state ``Q`` after it (``rec`` its record), below
    the window. Stages ``i, i + 1, ...`` whose windows lie above ``S_Q`` get states on the path from ``P`` to ``Q``
    (:class:`vnc_warp.remesh._SurfaceBlend`, the zero level set of ``(1 - a) f_P + a f_Q`` on a grid
    ``_BRIDGE_REFINE`` times finer than the remesher's), ``a`` searched from the previous bridged stage's toward 1
    (Illinois steps, at most ``_BRIDGE_TRIALS`` per stage) until ``t`` lands in the stage's window. Where ``t``
    jumps across a window along the path (a handle closes, a part goes, at some ``a``) the bracket shrinks to
    ``_BRIDGE_GAP``, and that stage records the first state past the jump (status ``bridge jump``, the genus-change
    exception); the stages after it are bridged as before. The path's first state, at ``a = _BRIDGE_GAP``, is made
    first: where it is already below stage ``i``'s window it is that jump, and a stage whose window the path has
    already passed (below the previous stage's jump) records the path's next state, ``_BRIDGE_GAP`` further, as its
    exception, without a search.

    Returns:
        ``([(state, record), ...], None)`` for the bridged stages, in order, or ``([], why)`` when the path lands no
        stage (its ``t`` jumps at ``a = 0+``: the grid cannot represent ``P``'s features) and the stage keeps ``Q``.
    """
    from .remesh import _SurfaceBlend

    t_start = time.perf_counter()
    mesh_p, x_p, S_p, kind = before
    origin = q.origin
    if x_p is None:
        x_p = wp.array(mesh_p.local_vertices, dtype=wp.vec3, device=device)

    def tri(mesh):
        return wp.array(np.ascontiguousarray(mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32, device=device)

    S_q = rec["S"]
    tol = p.tolerance * S_init
    try:
        blend = _SurfaceBlend(remesher, x_p, tri(mesh_p), wp.array(q.local_vertices, dtype=wp.vec3, device=device),
                              tri(q), spacing=remesher.spacing / _BRIDGE_REFINE)
    except MeshError as err:
        return [], f"no bridge over the remesh ({err})"
    cache: dict = {}

    def trial(a: float) -> tuple[float, Mesh | None, dict | None]:
        if a not in cache:
            try:
                mesh, report = blend(a)
            except MeshError as err:
                log.info("VNC-Flow: the bridge at a = %.4g failed (%s)", a, err)
                cache[a] = (math.nan, None, None)
            else:
                mesh = _as_saved(mesh, origin)
                cache[a] = (total_complexity(mesh, taus, kappa=p.kappa, device=device), mesh, report.to_dict())
        return cache[a]

    where = (f"{kind} took t from {S_p / S_init:.4f} to {S_q / S_init:.4f}, below stage {i}'s window; "
             f"stages {i}..")
    # the path's first state, a = _BRIDGE_GAP: where t has already jumped across stage i's window there (P's own
    # level set is about Q: its parts met, or parts thinner than the grid went), that state is stage i's jump, found
    # in one blend instead of a search toward a = 0 (FAUST 025 on the H200 at 36d1669: 4 blends, 26.5 s); a stage
    # whose window the path has passed already records the path's next state (one blend, not a search)
    S_g, mesh_g, report_g = trial(_BRIDGE_GAP)
    out, lo, S_lo, j, landed = [], 0.0, S_p, i, 0
    # the Euler characteristics on either side of the last jump along the path, (before, after)
    euler_p, jumped = _euler(mesh_p), None
    while j < p.stages and S_q < S_init * (1.0 - j / p.stages) - tol:
        target = S_init * (1.0 - j / p.stages)
        hi, S_hi, side, trials, history, found = 1.0, S_q, 0, 0, [[0, S_lo]], None
        passed = S_lo < target - tol
        if passed:
            hi = min(lo + _BRIDGE_GAP, 1.0)  # no search: the path's next state
        elif lo == 0.0 and math.isfinite(S_g):
            trials += 1
            history.append([trials, S_g])
            if abs(S_g - target) <= tol:
                found = (_BRIDGE_GAP, S_g, mesh_g, report_g)
            elif S_g > target:
                lo, S_lo = _BRIDGE_GAP, S_g
            else:
                hi, S_hi = _BRIDGE_GAP, S_g  # no search left: the jump lies within [0, _BRIDGE_GAP]
        while found is None and trials < _BRIDGE_TRIALS and hi - lo > _BRIDGE_GAP:
            gap = S_lo - S_hi
            theta = lo + (S_lo - target) / gap * (hi - lo) if gap > 0.0 else 0.5 * (lo + hi)
            a = min(max(theta, lo + 0.05 * (hi - lo)), hi - 0.05 * (hi - lo))
            S, mesh, report = trial(a)
            trials += 1
            history.append([trials, S])
            if not math.isfinite(S):
                hi = a  # a failed blend: look nearer the last good state
                continue
            if abs(S - target) <= tol:
                found = (a, S, mesh, report)
                break
            # Illinois steps (see _ellipsoid_blend)
            if S > target:
                lo, S_lo = a, S
                if side > 0:
                    S_hi = target + 0.5 * (S_hi - target)
                side = 1
            else:
                hi, S_hi = a, S
                if side < 0:
                    S_lo = target + 0.5 * (S_lo - target)
                side = -1
        jump = None
        if found is None:
            # t jumps across the window between a = lo and a = hi: the first state past the jump is the exception
            S_hi, mesh, report = trial(hi) if hi < 1.0 else (S_q, q, None)
            if mesh is None or hi >= 1.0:
                break
            if passed:
                trials += 1
                history.append([trials, S_hi])
            if not passed or jumped is None:
                before_jump = cache.get(lo, (None, None, None))[2] if lo > 0.0 else None
                went = (report["dropped_area"] >= _PART_AREA
                        and (before_jump or {}).get("dropped_area", 0.0) < _PART_AREA)
                jumped = (euler_p if before_jump is None else before_jump["euler"], report["euler"], went)
            # only a jump with a genus change or a part that went is the documented exception; a jump with the
            # topology unchanged (fandisk at 12,946 faces, CPU: stage 23, a fin thinner than the bridge's grid gone at
            # a = 0+, Euler characteristic 2 -> 2, pieces of 0.006 % of the area dropped) is a miss
            change = (f"Euler characteristic {jumped[0]} -> {jumped[1]}" + (
                ": a genus change" if jumped[0] != jumped[1] else
                f", a part of {100.0 * report['dropped_area']:.2f} % of the area dropped" if jumped[2] else
                ": no topology change, not the documented exception"))
            jump = (f"the bridge passed this stage's window at the previous stage's jump ({change}): recording its "
                    f"next state, a = {hi:.4g} (t {S_hi / S_init:.4f})" if passed else
                    f"t jumps across this stage's window along the bridge between a = {lo:.4g} (t {S_lo / S_init:.4f}"
                    f") and a = {hi:.4g} (t {S_hi / S_init:.4f}, {change}): recording the state past the jump")
            found = (hi, S_hi, mesh, report)
        a, S, mesh, report = found
        landed += jump is None
        r = {"index": i + len(out), "t": S / S_init, "S": S, "target_t": target / S_init, "iterations": 0,
             "evaluations": trials, "status": "bridge jump" if jump else "bridged",
             "exception": jump, "history": history, "remeshes_within": [], "remesh": None,
             "bridge": {"a": a, "trials": trials, "t_from": S_p / S_init, "t_to": S_q / S_init,
                        "over": kind, "first_stage": i, "remesh": report,
                        **({"jump_euler": list(jumped[:2]), "jump_topology": jumped[0] != jumped[1] or jumped[2]}
                           if jump else {})},
             "parts": {}, **_facts(mesh, device)}
        out.append((mesh, r))
        lo, S_lo, j = a, S, j + 1
    if not landed:
        return [], (f"{where} could not be bridged: no stage landed in its window along the level-set path "
                    f"({len(cache)} blend(s); t jumps at a = 0+ where the bridge's grid cannot represent the state "
                    f"before the remesh); recording the remeshed state")
    last = out[-1][1]
    for _, r in out:
        r["bridge"]["stages"] = [out[0][1]["index"], last["index"]]
        r["exception"] = "; ".join(x for x in (r["exception"], where + f"{last['index']} bridged") if x)
    out[0][1]["seconds_bridge"] = time.perf_counter() - t_start
    return out, None


def _merge_substages(subs: list[dict]) -> dict:
    """One stage record from its sub-stages' (:class:`FlowParams` ``substage_budget``): the last one's state, ``t``
    and status; iterations, evaluations, chord misses and seconds summed; the first one's remesh as the stage's, the
    later ones' with the remeshes within; the history on one iteration axis; the earlier sub-stages' exceptions kept."""
    rec = dict(subs[-1])
    if len(subs) == 1:
        return rec
    rec["remesh"] = subs[0].get("remesh")
    within, history, parts, notes, offset = [], [], {}, [], 0
    for j, sub in enumerate(subs):
        if j > 0 and sub.get("remesh"):
            within.append(sub["remesh"])
            parts["remesh"] = parts.get("remesh", 0.0) + sum(sub["remesh"].get("seconds", {}).values())
        within += sub.get("remeshes_within") or []
        history += [[offset + it, S] for it, S in sub["history"]]
        offset += sub["iterations"]
        for k, v in (sub.get("parts") or {}).items():
            parts[k] = parts.get(k, 0.0) + v
        if j < len(subs) - 1 and sub.get("exception"):
            notes.append(f"sub-stage {j + 1} of {len(subs)}: {sub['exception']}")
    if rec.get("exception"):
        notes.append(rec["exception"])
    misses = sum(sub.get("chord_misses", 0) for sub in subs)
    if misses:
        rec["chord_misses"] = misses
    rec.update(iterations=offset, evaluations=sum(s["evaluations"] for s in subs), history=history,
               remeshes_within=within, parts=parts, exception="; ".join(notes) or None,
               substages=[{"t": s["t"], "target_t": s["target_t"], "iterations": s["iterations"], "status": s["status"]}
                          for s in subs])
    return rec


def _digest_arrays(v: np.ndarray, f: np.ndarray) -> str:
    h = hashlib.sha256(np.ascontiguousarray(v, dtype=np.float32).tobytes())
    h.update(np.ascontiguousarray(f, dtype=np.int32).tobytes())
    return h.hexdigest()[:16]


def _facts(mesh: Mesh, device, positions: wp.array | None = None) -> dict:
    """Per-stage facts of a state, from the device: sphericity, relative thickness (5th percentile and thinnest part),
    counts, Euler."""
    surface = _Surface.of(mesh, device, positions)
    area, volume = surface.measures()
    span = surface.span()  # one read of the bounds for both kinds of rays
    return {"sphericity": float(36.0 * np.pi * volume**2 / area**3),
            "thickness": surface.relative_thickness(area, span=span),
            "thinnest": surface.thinnest_part(area, mesh.topology.edges, span),
            "vertices": mesh.num_vertices, "faces": mesh.num_faces,
            "euler": int(mesh.num_vertices - mesh.topology.edges.shape[0] + mesh.num_faces)}


def _run_stage(mesh: Mesh, i: int, taus, S_init: float, p: FlowParams, device, bar, rec: dict, remesher=None, *,
               goal: float | None = None, previous: dict | None = None, stepper_type: type = _Stepper):
    """Stage ``i`` on ``mesh`` (already remeshed): steps of Eq. (5) until ``t`` is within ``tolerance`` of
    ``1 - goal`` (default ``goal = i/N``; a sub-stage's is a fraction in between; see the module docstring); fills
    ``rec`` and returns the state and its device positions. A stage that stalls is remeshed on the way
    (``remesher``, if any; ``stall_remeshes``). ``previous``: the record of the stage (or sub-stage) before, whose
    fallback tells this one's where to start. ``stepper_type``: the class of the stage's steppers (Eq. 5 and ``S``;
    the fallbacks make their own), a subclass of :class:`_Stepper` in tests that inject how ``S`` is measured."""
    previous = previous or {}
    early_blend = previous.get("status") == "blended"
    from .remesh import _Clock

    parts: dict = {}
    clock = _Clock(device, parts)
    goal = i / p.stages if goal is None else goal
    final = goal >= 1.0
    target = S_init * (1.0 - goal)
    tol = p.tolerance * S_init
    stepper = stepper_type(mesh, taus, p, device)
    S_a = stepper.S_start if stepper.S_start is not None else stepper.complexity()
    # the last stage runs until S stops falling, and at the trajectory's fixed scales a shrinking shape lowers S
    # (_scaled_to_volume): its states are held at the volume it started with, as the continuous Eq. (5) keeps it
    # (its speed H - H_ref has zero area mean). Unheld, one H200 run shrank a body's last stage to a speck
    # (docs/results/cvae24_h200_f069d85: human0_0057, its last stage's sampling floor EMD 0.13 against 2.5-3.0)
    hold = stepper.volume() if final and p.method == "vnc" else None
    clock.lap("setup")
    history = [[0, S_a]]
    it, it_a, evaluations, stale, status = 0, 0, 1, 0, None
    S_seg, step_scale = S_a, 1.0
    x_a = wp.clone(stepper.x)
    # the fixed-scale ablations of Fig. 7 (c, d) keep the plain step: with backtracking the fixed small scale no
    # longer stalls (t 0.31 -> 0.15 at stage 2 of tests/test_flow.py's shape), which is not the paper's ablation;
    # and a shape with a handle must pass through a rise of S until a remesh closes the hole
    descent = p.method == "vnc" and p.scale_mode == "adaptive" and _euler(mesh) == 2
    # the thin-part correction of the best state, for a backtrack: after a rise (descent only) or a chord miss (any
    # stage of Eq. (5))
    part_a = wp.clone(stepper.part) if p.method == "vnc" else None
    # the stage's best state over its remeshes: (S, connectivity, positions)
    kept = None
    # a join of parts that met whose t is below the window, the topology unchanged: (mesh, report, stepper), taken
    # only where the smoothing fallback from the best state before it does not land the stage
    deferred = None
    contact = remesher is not None and p.method == "vnc"
    last_valid = mesh
    rate = None
    since, within, ahead, steady = 0, [], p.eval_every // 2, 0
    early = False
    # the overshoots whose chord held no state in the window: (S above it, S below it, the nearest trial's S)
    misses = []
    # a stage whose fallbacks can take it on goes to them as soon as Eq. (5) is seen to be too slow for its window
    cut, cut_ok = None, (not final and p.method == "vnc" and p.scale_mode == "adaptive" and p.early_fallback
                         and (p.smoothing_fallback or (p.blend_fallback and remesher is not None)))
    if not final and S_a <= target + tol:
        status = "remesh"
    while status is None:
        if it >= p.max_iters:
            status = "max_iters"
            break
        # steps to the next evaluation: to where the observed decay rate reaches the target; without a decay
        # (S rose), twice as many as last time
        ahead = 2 * ahead if rate is None else int(np.ceil((S_a - target) / rate))
        ahead = max(p.eval_every, min(ahead, p.eval_max))
        for _ in range(min(ahead, p.max_iters - it)):
            stepper.step()
            it += 1
        if hold is not None:
            stepper.hold_volume(hold)
        clock.lap("steps")
        if p.method != "vnc":
            if _check_state(stepper.current()):
                status = "collapsed"
                break
            last_valid = stepper.current()
        S_b = stepper.complexity()
        evaluations += 1
        clock.lap("evaluations")
        history.append([it, S_b])
        if bar is not None:
            bar.set_postfix(stage=i, it=it, t=f"{S_b / S_init:.3f}")
        # where the stage goes on from a remesh of: parts touching, or a stall. Parts are looked for while the stage
        # is above its window only: a join there is part of the stage's descent, one after it landed would take t
        # below the window (the next stage's remesh joins what little overlap the last run of steps made)
        restart = None
        # not a descent: the run of steps since the best state raised S above the segment's start (beyond the
        # re-smoothing of a remeshed state), or climbed past the minimum of Eq. (5) at this step
        climbed = descent and S_b > target + tol and (
            S_b > S_seg * (1.0 + _RISE) + _RISE_INIT * S_init or (S_a < S_seg and S_b > S_a + _CLIMB * tol))
        # A run that climbed is taken back (below) whether or not its parts met: the best state before it did not
        # touch (it was checked at its evaluation), and a join of the climbed state is a join of a state the stage
        # does not keep. On the H200 at 765207b fandisk's stage 23 climbed from t 0.290 to 0.339 in 16 steps into a
        # contact, whose join took t to 0.235 (window 0.281 +- 0.005), a level-set remesh with the Euler
        # characteristic unchanged (2 -> 2); armadillo's stage 15 likewise (0.546 -> 0.598, join 0.506, window
        # 0.531), and scorpion's stages 3 and 7
        touching = (S_b > target + tol and contact and len(within) < p.stall_remeshes and not climbed
                    and remesher.interpenetrates(stepper.x))
        clock.lap("checks")
        if touching:
            # Parts that moved into each other (two legs fattening side by side, a sheet folded over) are no surface
            # of a shape: topology regularization joins them where they touch, now, rather than letting the flow go
            # on through a self-intersection that the stage would record (see the module docstring)
            restart = stepper.x
        elif S_b > target + tol:
            rate = (S_a - S_b) / (it - it_a) if S_b < S_a else None
            # S need not fall at every step (a remeshed state is re-smoothed first): only a run of
            # evaluations without a new low counts as a stall
            stale = stale + 1 if S_b > S_a * (1.0 - _PROGRESS) else 0
            if S_b < S_a:
                wp.copy(x_a, stepper.x)
                if part_a is not None:
                    wp.copy(part_a, stepper.part)
                if descent and not final and S_b < S_a * (1.0 - _PROGRESS):
                    # the step held: the next run of steps may take larger ones (see FlowParams.step_growth). Not in
                    # the last stage, which runs until S stops falling: there a grown step ended where float32
                    # rounding decided (tests/test_flow.py, the flow far from the origin: t 0.0111 against 0.0076)
                    if stepper.grow():
                        rate *= p.step_growth
                S_a, it_a = S_b, it
            elif climbed:
                # not a descent: go back to the best state and halve the step
                stepper.backtrack(x_a, part_a)
                ahead = p.eval_every // 2
                history.append([it, S_a])
                steady = it
            if early_blend and stale >= _EARLY_STALE and not final and remesher is not None:
                # a stage that starts from a blended state and makes no progress goes to the blend at once
                early = True
                status = "converged"
                continue
            if cut_ok and descent and not stepper.can_grow():
                need = _iterations_needed(history, max(since, steady), it, S_a, target + tol, 2 * p.eval_max)
                if need is not None and need > _CUT_MARGIN * (p.max_iters - it):
                    # Eq. (5) at its step (grown as far as it goes) cannot reach the window in the iterations left:
                    # the fallback now, rather than after max_iters and the stall remeshes on the way. The rate is
                    # measured since the last backtrack (a run of steps taken back leaves the best S where it was)
                    cut = (need, p.max_iters - it)
                    status = "converged"
                    continue
            if stale >= p.patience and it - since >= 4 * p.eval_max:
                if final or remesher is None or p.method != "vnc" or len(within) >= p.stall_remeshes:
                    status = "final" if final else "converged"
                    continue
                # a stalled stage is remeshed from its best state and goes on (a state far from a regular
                # tessellation stalls: the remains of a bunny's ears folded, a dumbbell's neck settled). A shape
                # with a handle (Euler characteristic below 2) that never got below its start is passing
                # through a rise of S, its hole narrowing until a remesh closes it (the genus-change
                # exception): it is remeshed where the flow went, or every stage would restart from one state.
                # Any other shape whose S never fell had a step too large for it (a near-sphere, where the
                # 90th-percentile deviation is small and lambda sits at max_lambda): it goes on at half the step
                stuck = not S_a < S_seg * (1.0 - _PROGRESS)
                through = stuck and _euler(mesh) < 2
                if stuck and not through:
                    step_scale *= 0.5
                restart = stepper.x if through else x_a
            if restart is None:
                continue
        else:
            if S_b < target - tol:
                S_c, found = _search_chord(stepper, x_a, S_a, S_b, target, tol, history, it_a, it)
                evaluations += found
                clock.lap("evaluations")
                if abs(S_c - target) > tol:
                    # no state on the chord lands in the window (S jumps along it: a thorn formed): not the
                    # stage's budget. Back to the best state above the window at half the step, as after a rise;
                    # the baselines have no step to halve, and a stage out of retries ends above its window
                    misses.append((S_a, S_b, S_c))
                    if p.method == "vnc" and len(misses) <= _CHORD_RETRIES:
                        stepper.backtrack(x_a, part_a)
                        ahead = p.eval_every // 2
                        history.append([it, S_a])
                        steady = it
                    else:
                        status = "missed"
                    continue
                S_b = S_c
            status = "budget"
            S_a = S_b
            continue
        if descent and (kept is None or S_a < kept[0]):
            kept = (S_a, mesh, wp.clone(x_a))
        # the bridge (flow()) goes from the best state before the stage's last remesh, should it skip the window
        rec["before_remesh"] = (mesh, wp.clone(x_a), S_a, "a level-set remesh within the stage")
        try:
            joined, report = remesher(positions=restart)
        except MeshError as err:
            if not touching:
                raise
            # parts tangled beyond a clean join (an oversized step folded the surface through itself): no state to
            # go on from; back to the stage's best state at half the step, with no more joins in this stage
            log.info("VNC-Flow stage %d: no join of the parts that met (%s); back to the best state", i, err)
            contact = False
            if descent:
                stepper.backtrack(x_a, part_a)
            else:
                wp.copy(stepper.x, x_a)
            ahead = p.eval_every // 2
            history.append([it, S_a])
            continue
        following = stepper_type(joined, taus, p, device, step_scale=step_scale)
        if (touching and not final and descent and p.smoothing_fallback and following.S_start < target - tol
                and report.euler == report.euler_in and report.dropped_area < _PART_AREA):
            # The join would take t below the window with the topology unchanged (the Euler characteristic kept,
            # no part dropped): what it removes is no handle or part but S the level set cannot hold, a fin or
            # crease thinner than the grid that folded into the shape (fandisk at 12,946 faces, CPU, stage 23 of
            # 32: t 0.293 -> 0.203 for the window 0.281 +- 0.005, 34 vertices inside another part, the fin's two
            # fragments, 0.008 % of the area, dropped). Neither the bridge (the fin is thinner than its grid too: t
            # jumps at a = 0+) nor a later stage can land a state in this window on the level-set path, so the
            # stage smooths its best state before the contact into the window instead (the smoothing fallback)
            # and takes the join only where that does not land it
            deferred = (joined, report, following)
            status = "converged"
            continue
        mesh = joined
        within.append(report.to_dict())
        stepper = following
        S_a, it_a, since, rate, stale, ahead = stepper.S_start, it, it, None, 0, p.eval_every // 2
        S_seg = S_a
        x_a = wp.clone(stepper.x)
        part_a = wp.clone(stepper.part)
        descent = p.scale_mode == "adaptive" and _euler(mesh) == 2
        history.append([it, S_a])
        clock.lap("remesh")
        if touching and not final and S_a <= target + tol:
            # the join already took S into or below the window: the stage records it, as a stage whose remesh
            # between stages did
            status = "remesh"
    if status in ("max_iters", "converged", "final", "missed"):
        # a stage that cannot go on keeps its best state, also one from before a remesh within the stage
        wp.copy(stepper.x, x_a)
        if kept is not None and kept[0] < S_a:
            S_a, stepper.mesh, stepper.x = kept
            rec["kept"] = True
    smoothed = None
    # not the last stage: its target t = 0 is out of reach by design (see its exception), and no later stage can
    # repeat its state
    if (status in ("max_iters", "converged", "missed") and not final and S_a > target + tol and p.method == "vnc"
            and p.scale_mode == "adaptive" and not early and p.smoothing_fallback):
        smoothed = _smoothing_fallback(stepper, taus, p, device, S_a, target, tol, history, it,
                                       start=(previous.get("smoothing") or [None])[-1])
        if smoothed is not None:
            stepper, S_a, found, steps = smoothed
            evaluations += found
            rec["kept"] = True
            rec["smoothing"] = [[kind, dt] for kind, dt in steps]
            clock.lap("fallback")
    if deferred is not None:
        joined, report, following = deferred
        join = report.to_dict()
        rec["deferred_join"] = {"t": following.S_start / S_init, "taken": False, **{
            k: join[k] for k in ("euler_in", "euler", "components_level_set", "dropped_components", "dropped_area",
                                 "lost_area", "why_level_set")}}
        # the smoothed state is kept where it is nearer the target than the join (in the window, or short of it by
        # less: on the H200 at 1ef098c fandisk's stage 22 smoothed to t 0.3066 for the window 0.3125 +- 0.005, and
        # the join took it to 0.2919)
        nearer = smoothed is not None and abs(S_a - target) < abs(following.S_start - target)
        joined_held = None
        if nearer:
            # the remesher holds the join it made, a surface the stage has not taken: the smoothed state goes into it
            # first, or the contact check below (and the next stage's remesh) would read the smoothed state's
            # positions on the join's connectivity (on the H200 at 1ef098c: a copy of 3,002 positions into 2,999,
            # three humanoids and armadillo.obj failed)
            joined_held = remesher.held()
            remesher.adopt(stepper.current(), remesher.spacing, remesher.name)
        if not nearer or remesher.interpenetrates(stepper.x):
            # the smoothing fallback did not come nearer the window than the join (or its parts met too): the join
            # after all, as before
            if joined_held is not None:
                remesher.restore(joined_held)
            rec["deferred_join"].update(taken=True, smoothed_t=None if smoothed is None else S_a / S_init)
            mesh, stepper, smoothed = joined, following, None
            rec.pop("smoothing", None)
            within.append(join)
            S_a = stepper.S_start
            history.append([it, S_a])
            status = "remesh"
    blended = None
    if (status in ("max_iters", "converged", "missed") and not final and S_a > target + tol and p.method == "vnc"
            and p.scale_mode == "adaptive" and remesher is not None and p.blend_fallback):
        blended = _ellipsoid_blend(stepper, taus, p, device, remesher, S_a, target, tol, history,
                                   it + evaluations)
        if blended is not None:
            stepper, S_a, trials, a, report = blended
            evaluations += trials
            rec["kept"] = True
            rec["blend"] = {"a": a, "trials": trials, "remesh": report.to_dict()}
            clock.lap("blend")
    if status == "collapsed":
        state = last_valid
        S_a = total_complexity(state, taus, kappa=p.kappa, device=device)
    else:
        state = stepper.current()
    exception = None
    remesh = rec.get("remesh")
    if remesh and remesh["euler"] != remesh["euler_in"]:
        exception = (f"the remesh changed the topology (Euler characteristic {remesh['euler_in']} -> "
                     f"{remesh['euler']}: {remesh['why_level_set']})")
    closed = [r for r in within if r["euler"] != r["euler_in"]]
    if closed:
        exception = ((exception + "; ") if exception else "") + (
            f"a remesh within the stage changed the topology (Euler characteristic {closed[0]['euler_in']} -> "
            f"{closed[-1]['euler']}: {closed[0]['why_level_set']})")
    if status == "remesh":
        if exception is None and remesh and remesh["method"] == "level_set":
            exception = f"the level-set remesh ({remesh['why_level_set']})"
        exception = (exception or "the remesh") + f" took t to {S_a / S_init:.4f}, into or below this stage's window"
        if deferred is not None:
            smoothed_t = rec["deferred_join"]["smoothed_t"]
            exception += (f" (a join of parts that met, the topology unchanged; the smoothing fallback from the best "
                          f"state before it " + ("found no step that lowers S" if smoothed_t is None else
                                                 f"ended at t {smoothed_t:.4f}") + ")")
    elif status == "final":
        exception = (f"last stage: target t = 0 is below a meshed sphere's VNC-AUC; ran until S stopped "
                     f"decreasing at the volume it started with, at t = {S_a / S_init:.4f}")
    elif status in ("max_iters", "converged", "missed"):
        if cut is not None:
            stop = f"too slow after {it} iterations"
        elif status == "missed":
            stop = f"no state in the window after {it} iterations"
        else:
            stop = f"{status} after {it} iterations"
        # a stage that passed its window without landing in it did descend
        failed = "did not land in the window" if status == "missed" else "did not descend"
        if deferred is not None:
            join = rec["deferred_join"]
            failed, stop = "stopped", (
                f"its parts met after {it} iterations, and their join, a level-set remesh with the topology unchanged "
                f"(Euler characteristic {join['euler_in']} -> {join['euler']}, {join['dropped_components']} level-set "
                f"piece(s) of {100.0 * join['dropped_area']:.3f} % of its area dropped), would take t to "
                f"{join['t']:.4f}, below the window")
        if misses:
            S_hi, S_lo, S_near = misses[-1]
            retried = len(misses) - (status == "missed")
            exception = ((exception + "; ") if exception else "") + (
                f"{len(misses)} run(s) of steps overshot the window with no state in it on their chord (S jumps "
                f"along the chord; the last from t {S_hi / S_init:.4f} to {S_lo / S_init:.4f}, its nearest trial "
                f"{S_near / S_init:.4f})" + (f"; {retried} backtrack(s) to the best state above the window at half the "
                                              "step" if retried else "; a baseline has no step to halve"))
        if cut is not None:
            exception = ((exception + "; ") if exception else "") + (
                f"Eq. (5) at its rate over the last {2 * p.eval_max} iterations would need {cut[0]:.0f} more to reach "
                f"the window, {cut[1]} were left: fallback at iteration {it}")
        if early:
            exception = ((exception + "; ") if exception else "") + (
                f"from a blended state, no progress in {stale} evaluations; no smoothing tried")
        if smoothed is not None:
            exception = ((exception + "; ") if exception else "") + (
                f"Eq. (5) {failed} ({stop}); {len(smoothed[3])} implicit smoothing "
                f"step(s) ({', '.join(f'{kind} dt {d:g}' for kind, d in smoothed[3])}; dt in squared edge lengths) "
                f"took t to "
                f"{smoothed[1] / S_init:.4f} (target {max(target, 0.0) / S_init:.4f})")
            if abs(S_a - target) <= tol and blended is None:
                status = "smoothed"
        elif blended is None:
            exception = ((exception + "; ") if exception else "") + (
                f"{status} after {it} iterations at t = {S_a / S_init:.4f} (target {max(target, 0.0) / S_init:.4f}); "
                + ("recording the best state above the window" if status == "missed" else "recording the t reached"))
        if blended is not None:
            if smoothed is None:
                exception = ((exception + "; ") if exception else "") + (
                    f"Eq. (5) {failed} ({stop})")
            exception += (f"; the SDF {blended[4].why_level_set} ({blended[2]} trial(s)) took t to {S_a / S_init:.4f} (target {max(target, 0.0) / S_init:.4f})")
            if abs(S_a - target) <= tol:
                status = "blended"
    if misses:
        # a stage that landed after a chord miss has no exception; its record says how many chords it searched in vain
        rec["chord_misses"] = len(misses)
    rec.update(t=S_a / S_init, S=S_a, target_t=max(target, 0.0) / S_init, iterations=it, evaluations=evaluations,
               status=status, exception=exception, history=history, remeshes_within=within,
               **_facts(state, device, None if status == "collapsed" else stepper.x))
    clock.lap("record")
    rec["parts"] = parts
    return state, stepper.x


def _scaled_to_volume(x: wp.array, tri: wp.array, volume: float, device) -> wp.array:
    """``x`` scaled about its vertex centroid to enclose ``volume``. ``S`` is measured at the trajectory's fixed
    scales, where the same shape scores lower the smaller it is (a near-sphere of human0_0057's last stage: t 0.049
    at its size, 0.028 at half of it, 0.006 at a tenth) and higher the larger: where a step's volume is not the
    flow's to choose, it is scaled back."""
    now = float(face_measures(x, tri)[1])
    if not (now > 0.0 and volume > 0.0):
        return x
    v = x.numpy().astype(np.float64)
    c = v.mean(axis=0)
    v = c + (v - c) * (volume / now) ** (1.0 / 3.0)
    return wp.array(v.astype(np.float32), dtype=wp.vec3, device=device)


def _smoothing_fallback(stepper: _Stepper, taus, p: FlowParams, device, S_a: float, target: float, tol: float,
                        history: list, it: int, *, start=None):
    """Backward-Euler smoothing steps from the stage's best state, for a stage where Eq. (5) stands still or climbs
    ``S``: ``(M - dt L) x' = M x + dt c 2 H_ref A n``, with ``L`` the cotangent Laplacian (``L x = -2 H A n``),
    ``M = A`` the vertex areas, ``H_ref`` the area mean of ``H`` and ``dt`` in squared mean edge lengths. ``c = 0`` is
    mean curvature flow, the implicit baseline of Fig. 7 (f); ``c = 1`` moves each vertex by about
    ``-2 dt (H - H_ref) n``, Eq. (5) at the vertex's own scale, which keeps the shape from shrinking. The steps are
    tried in the order (mean curvature flow, with the mean) at ``dt = _FALLBACK_DT``, then at ``_FALLBACK_GROWTH``
    times that, up to ``_FALLBACK_DT_MAX``: a step that lowers ``S`` is kept and repeated, one that does not is undone
    and the next kind is tried (at most ``_FALLBACK_TRIES`` evaluations of ``S``); the last is searched back on its
    chord into the window. ``start``: the ``(kind, dt)`` that the previous stage's fallback ended with, where this
    one starts (the ones before it come last): a state that needed a large ``dt`` (the hammer at 6,000 faces: 256)
    needs it again, and each kind tried and undone costs an evaluation of ``S`` and a factorization. Returns ``(stepper,
    S, evaluations, steps)`` with the smoothed state and the kept steps as
    ``(kind, dt)`` (``"mcf"`` or ``"mean"``), or None when no step lowers ``S``."""
    from scipy.sparse.linalg import factorized

    q = dataclasses.replace(p, method="mcf_implicit", mcf_dt=_FALLBACK_DT)
    smoother = _Stepper(stepper.current(), taus, q, device)
    area = smoother.M.diagonal()
    kinds = []
    dt = _FALLBACK_DT
    while dt <= _FALLBACK_DT_MAX:
        kinds += [("mcf", dt), ("mean", dt)]
        dt *= _FALLBACK_GROWTH
    if start is not None and tuple(start) in kinds:
        k = kinds.index(tuple(start))
        kinds = kinds[k:] + kinds[:k]
    solvers = {_FALLBACK_DT: smoother.solve}
    x_a = wp.clone(smoother.x)
    S_best, evaluations, steps, k = S_a, 0, [], 0
    while evaluations < _FALLBACK_TRIES and k < len(kinds):
        kind, dt = kinds[k]
        if dt not in solvers:
            solvers[dt] = factorized((smoother.M - (dt * smoother.edge**2) * smoother.L).tocsc())
        v = smoother.x.numpy().astype(np.float64)
        rhs = smoother.M @ v
        if kind == "mean":
            n = vertex_normals(smoother.x, smoother.surface.tri).numpy().astype(np.float64)
            two_h_ref = -float(np.sum((smoother.L @ v) * n)) / float(area.sum())
            rhs = rhs + (dt * smoother.edge**2 * two_h_ref) * area[:, None] * n
        volume = face_measures(smoother.x, smoother.surface.tri)[1] if kind == "mean" else None
        v = np.stack([solvers[dt](rhs[:, d]) for d in range(3)], axis=1)
        smoother.x = wp.array(v.astype(np.float32), dtype=wp.vec3, device=device)
        if volume is not None:
            # the continuous flow keeps the volume; the step's explicit mean does not quite (the capsule hammer at
            # dt 16: +57 %): scaled back to the volume it had
            smoother.x = _scaled_to_volume(smoother.x, smoother.surface.tri, volume, device)
        S = smoother.complexity()
        evaluations += 1
        history.append([it + evaluations, S])
        if not S < S_best:
            wp.copy(smoother.x, x_a)
            k += 1
            continue
        steps.append((kind, dt))
        if S < target - tol:
            S, found = _search_chord(smoother, x_a, S_best, S, target, tol, history, it + evaluations - 1,
                                     it + evaluations)
            return smoother, S, evaluations + found, steps
        S_best = S
        wp.copy(x_a, smoother.x)
        if S <= target + tol:
            break
    if not steps:
        return None
    wp.copy(smoother.x, x_a)
    return smoother, S_best, evaluations, steps


def _ellipsoid_blend(stepper: _Stepper, taus, p: FlowParams, device, remesher, S_a: float, target: float,
                     tol: float, history: list, it: int):
    """The last fallback of a stage that Eq. (5) and the smoothing fallback leave above its window: the zero level
    set of ``(1 - a) f + a g`` (``f`` the best state's signed distance, ``g`` its moment ellipsoid's; see
    :class:`vnc_warp.remesh._EllipsoidBlend`), with ``a`` in (0, 1] searched (secant steps in a bracket, bisection
    where ``S`` does not fall along it) until ``t`` lands in the window. Returns ``(stepper, S, trials, a, report)``
    for the blended state nearest the target among those below ``S_a``, or None when no blend lowers ``S``."""
    from .remesh import _EllipsoidBlend

    tri = wp.array(np.ascontiguousarray(stepper.mesh.faces, dtype=np.int32).reshape(-1), dtype=wp.int32,
                   device=stepper.x.device)
    try:
        blend = _EllipsoidBlend(remesher, stepper.x, tri)
    except MeshError as err:
        log.info("VNC-Flow: no blend toward the moment ellipsoid (%s)", err)
        return None
    best, trials = None, 0

    def trial(a: float) -> float:
        nonlocal best, trials
        trials += 1
        try:
            mesh, report = blend(a)
        except MeshError as err:
            log.info("VNC-Flow: the blend at a = %.4g failed (%s)", a, err)
            return math.inf
        st = _Stepper(mesh, taus, p, device)
        S = st.S_start
        history.append([it + trials, S])
        if S < S_a and (best is None or abs(S - target) < abs(best[1] - target)):
            best = (st, S, a, report, blend.roundness)
        return S

    for blend.roundness in _BLEND_ROUNDNESS:
        lo, S_lo, hi = 0.0, S_a, 1.0
        S_hi = trial(hi)
        # the state's own ellipsoid first; one too elongated to reach the window (a long handle's) gives way to the
        # sphere of its volume
        if S_hi <= target + tol or trials >= _BLEND_TRIALS:
            break
    side = 0
    if S_hi < target - tol:
        while trials < _BLEND_TRIALS:
            gap = S_lo - S_hi
            theta = lo + (S_lo - target) / gap * (hi - lo) if gap > 0.0 and math.isfinite(gap) else 0.5 * (lo + hi)
            a = min(max(theta, lo + 0.05 * (hi - lo)), hi - 0.05 * (hi - lo))
            S = trial(a)
            if abs(S - target) <= tol:
                break
            # Illinois steps: S falls steeply at small a and flattens toward the ellipsoid, so plain secant steps
            # keep landing on one side; the end kept twice in a row counts half as far from the target
            if S > target:
                lo, S_lo = a, S
                if side > 0:
                    S_hi = target + 0.5 * (S_hi - target)
                side = 1
            else:
                hi, S_hi = a, S
                if side < 0:
                    S_lo = target + 0.5 * (S_lo - target)
                side = -1
    if best is None:
        return None
    st, S, a, report, _ = best
    return st, S, trials, a, report


def _iterations_needed(history: list, since: float, it: int, S_a: float, S_goal: float, window: int) -> float | None:
    """The iterations Eq. (5) needs to take its best ``S_a`` down to ``S_goal`` at the rate it lowered its best ``S``
    over its last ``window`` iterations (``history``'s ``[iteration, S]`` since the segment's start ``since``): a
    linear extrapolation of a decay that slows down, so a lower bound. None while the segment is shorter than
    ``window`` or its best ``S`` did not fall over it (a stall: see ``patience``)."""
    back = [S for j, S in history if since <= j <= it - window]
    if not back:
        return None
    fell = min(back) - S_a
    return (S_a - S_goal) * (it - max(j for j, _ in history if since <= j <= it - window)) / fell if fell > 0 else None


def _search_chord(stepper: _Stepper, x_a: wp.array, S_a: float, S_b: float, target: float, tol: float,
                  history: list, it_a: int, it_b: int) -> tuple[float, int]:
    """Land ``S`` in ``[target - tol, target + tol]`` on the chord from ``x_a`` (``S_a`` above the window) to the
    current state (``S_b`` below it): secant steps on the chord fraction, each bracket kept. Leaves the state
    found in ``stepper.x``; returns its ``S`` and the evaluations made. Where no trial lands in the window (``S``
    jumps along the chord), the trial nearest the target (or the chord's end) is left and its ``S`` returned: the
    caller checks the window (a stage backtracks, see :func:`_run_stage`)."""
    x_b = wp.clone(stepper.x)
    lo, hi, S_lo, S_hi = 0.0, 1.0, S_a, S_b
    best, best_S = 1.0, S_b

    def trial(theta: float) -> float:
        """The state at ``theta`` along the chord, into ``stepper.x``; its ``S`` (kept as the best if nearest)."""
        nonlocal best, best_S
        wp.launch(_k.lerp_positions, dim=x_b.shape[0], inputs=[x_a, x_b, float(theta)], outputs=[stepper.x],
                  device=x_b.device)
        S = stepper.complexity()
        history.append([it_a + theta * (it_b - it_a), S])
        if abs(S - target) < abs(best_S - target):
            best, best_S = theta, S
        return S

    for k in range(1, 9):
        gap = S_lo - S_hi
        # A bracket whose ends have one S (a step that moved S by nothing measurable) or whose S rises along the
        # chord has no secant root inside it: bisect it.
        theta = lo + (S_lo - target) / gap * (hi - lo) if gap > 0.0 and math.isfinite(gap) else 0.5 * (lo + hi)
        theta = min(max(theta, lo + 0.05 * (hi - lo)), hi - 0.05 * (hi - lo))
        S = trial(theta)
        if abs(S - target) <= tol:
            return S, k
        if S > target:
            lo, S_lo = theta, S
        else:
            hi, S_hi = theta, S
    # S need not be monotone along the chord: where the bracket closed on a jump, a state in the window may lie
    # elsewhere on it (fandisk at 12,946 faces, CPU, the smoothing fallback of stage 23 of 32, window 0.281 +- 0.005:
    # t 0.2985, 0.2919, 0.2803, 0.2730, 0.2872, 0.2871, 0.2728 at fractions 0.825 ... 0.855 of the chord in steps of
    # 0.005; the secant search ended at 0.2871). The chord is scanned at _CHORD_SCAN evenly spaced fractions
    for k in range(1, _CHORD_SCAN + 1):
        S = trial(k / (_CHORD_SCAN + 1))
        if abs(S - target) <= tol:
            return S, 8 + k
    wp.launch(_k.lerp_positions, dim=x_b.shape[0], inputs=[x_a, x_b, float(best)], outputs=[stepper.x],
              device=x_b.device)
    return best_S, 8 + _CHORD_SCAN


def _version() -> str:
    from ._version import __version__

    return __version__
