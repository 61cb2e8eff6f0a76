"""Typed configuration objects that read YAML.

Two layouts are accepted:

* the project's own layout: top-level sections named like the dataclasses below
  (``sensor``, ``contact``, ``curvature``, ``normalflow``, ``tracking``, ``loop``,
  ``posegraph``, ``recon``); any section or key may be omitted;
* the public GelSLAM ``config.yaml`` layout (``device_config``, ``contact_mask_config``,
  ``gelslam_config``), including its misnamed ``ppmm`` key, which there as here means
  millimetres per pixel.

Pixel-valued constants that depend on the sensor (erosion sizes, areas in pixels) are
derived from :class:`SensorConfig` by properties rather than stored, so a DIGIT config
gets the right values without extra keys.
"""

from __future__ import annotations

import dataclasses
import math
import os
import re
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

PACKAGE_ROOT = Path(__file__).resolve().parent
REPO_ROOT = PACKAGE_ROOT.parent
MODELS_DIR = REPO_ROOT / "models"
GELSIGHT_MINI_ENV = "TACTILE_SLAM_GELSIGHT_MINI"


def gelsight_mini_data() -> Path:
    """The real GelSight Mini data folder (calibration presses, their ``background.png``,
    the sensor maker's reference model): ``$TACTILE_SLAM_GELSIGHT_MINI`` when set, else
    ``../shared/data/gelsight_mini`` beside the checkout. A checkout elsewhere (a git
    worktree under /tmp) finds nothing there: set the variable."""
    return Path(os.environ.get(GELSIGHT_MINI_ENV) or REPO_ROOT.parent / "shared" / "data" / "gelsight_mini")


class ConfigError(ValueError):
    """A configuration file or value is invalid."""


def resolve_device(name: str) -> str:
    """A torch device name this machine has: ``"auto"`` -> ``"cuda"`` when present, else
    ``"cpu"``; ``cpu``, ``cuda`` and ``cuda:N`` are checked. Raises :class:`ConfigError`
    naming the device otherwise."""
    import torch

    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    try:
        dev = torch.device(name)
    except RuntimeError as exc:
        raise ConfigError(f"unknown device {name!r} (use cpu, cuda, cuda:N or auto)") from exc
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            build = "a CPU-only build" if torch.version.cuda is None else f"CUDA {torch.version.cuda}, no GPU visible"
            raise ConfigError(f"{name}: CUDA is not available (torch {torch.__version__}, {build})")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"{name}: only {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        raise ConfigError(f"unsupported device {name!r} (use cpu, cuda, cuda:N or auto)")
    return name


@dataclass
class SensorConfig:
    """Sensor geometry and timing.

    ``mm_per_px`` is millimetres per pixel (GelSLAM's ``ppmm`` means the same).
    ``model_path`` is the calibration model, absolute or relative to the config file;
    ``None`` means the packaged default for this sensor, if any.
    """

    name: str = "GelSight Mini"
    mm_per_px: float = 0.0634
    width: int = 320
    height: int = 240
    raw_width: int = 3280
    raw_height: int = 2464
    fps: float = 25.0
    model_path: str | None = None
    background_frames: int = 10
    max_indentation_mm: float = 2.0

    @property
    def m_per_px(self) -> float:
        return self.mm_per_px / 1000.0

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the working image."""
        return (self.height, self.width)

    def px_from_mm2(self, area_mm2: float) -> float:
        return area_mm2 / (self.mm_per_px**2)

    def resolved_model_path(self) -> Path | None:
        if self.model_path is None:
            default = MODELS_DIR / f"{self.name.lower().replace(' ', '_')}.pt"
            return default if default.exists() else None
        return Path(self.model_path)


def min_image_px(blur_ksize: int) -> int:
    """Smallest image side curvature works on: 2 px for central differences, and more than
    half the blur kernel for its reflected border (:mod:`tactile_slam.geometry.curvature`)."""
    return max(blur_ksize // 2 + 1, 2)


def lower_limit(general: float | None, decoded_only: float | None, decoded: bool) -> float | None:
    """The limit that holds for a frame: ``general``, and for a frame decoded from an image
    also ``decoded_only``, the lower where both apply; None where neither does (the slope
    limits of :class:`NormalFlowConfig`, the tilt limits of :class:`TrackingConfig`)."""
    limits = [x for x in (general, decoded_only if decoded else None) if x is not None]
    return min(limits) if limits else None


@dataclass
class ContactConfig:
    """Contact-mask rule (method.md section 3.2) and the in-contact test (3.3).

    ``final_erode`` of ``None`` derives the final erosion size as max(H // 48, 1).
    ``min_contact_mm2`` is the in-contact area: 500 px on a GelSight Mini.
    """

    color_dist_threshold: float = 15.0
    dilate: int = 7
    erode: int = 15
    # depth test (geometry/contact.py): pixels deeper than height_threshold_mm (the public
    # SDK's rule, which drops touches not much deeper than it), or, for a shallower touch,
    # deeper than height_fraction of its deepest point (at least min_depth_mm);
    # height_fraction None: the fixed threshold alone. README, "Frame geometry".
    height_fraction: float | None = 0.5
    min_depth_mm: float = 0.05
    height_threshold_mm: float = 0.2
    height_percentile: float = 85.0
    final_erode: int | None = None
    min_contact_mm2: float = 500 * 0.0634**2
    # Fill enclosed holes of the colour mask (a pressed ball's flat bottom keeps the
    # background's colour); the public code does not. The height rule still applies.
    fill_holes: bool = True
    # Pixels whose colour differs from the background by less than this skip the
    # calibration MLP (their gradient is exactly the background's, i.e. zero).
    mlp_skip_color_dist: float = 8.0
    # Contact masks given with gradient maps: "final" uses them as the eroded mask as-is
    # (masks from another pipeline); "region" treats them like the colour mask of an image,
    # so the depth test and the final erosion above apply inside them (docs/io.md).
    given_masks: str = "final"


GIVEN_MASKS = ("final", "region")
"""``ContactConfig.given_masks`` values."""


@dataclass
class CurvatureConfig:
    """Curvature blur and clip (method.md section 3.3)."""

    blur_ksize: int = 5
    blur_sigma: float = 1.1
    clip: float = 0.7


TRACKING_INITS = ("constant_position", "constant_velocity")
"""``TrackingConfig.init`` values."""
KEYFRAME_EDGES = ("forward", "reverse", "midpoint")
"""``TrackingConfig.keyframe_edge`` values."""
LOOP_DETECTOR_MODES = ("full", "only_sift", "only_nf", "image_sift")
"""``LoopConfig.mode`` values (method.md 9.5)."""
FEATURE_MAPS = ("laplacian", "gaussian")
"""``LoopConfig.feature_map`` values: the curvature map SIFT runs on."""
SIFT_BACKENDS = ("opencv", "kornia")
"""``LoopConfig.sift_backend`` values."""
MERGE_DISTINCT = ("queries", "both")
"""``LoopConfig.merge_distinct`` values: the loop gate's rules for independent support."""
ROBUST_MODES = ("none", "huber", "cauchy", "gnc")
"""``PoseGraphConfig.robust`` values."""
FACTOR_KEYS = ("normalflow.coarse_factors", "normalflow.fallback_factors", "tracking.fallback_factors")
"""Block-averaging factors, which must divide the image size (:meth:`Config.check_factors`)."""
JACOBIAN_KINDS = ("analytic", "autograd")
"""``NormalFlowConfig.jacobian`` values (``registration.jacobian``'s closed form and torch.func)."""
SAMPLE_SELECTIONS = ("spread", "topk", "threshold", "random")
"""``NormalFlowConfig.selection`` values (``registration.sampling.select_samples``)."""


@dataclass
class NormalFlowConfig:
    """NormalFlow registration parameters (method.md section 4).

    ``n_samples`` of ``None`` uses every contact pixel. ``selection``: ``"spread"``
    (default: the top |L| within ``sample_cell_px``-square cells, each cell's share of
    ``n_samples`` proportional to its contact pixels, so that the samples cover a large
    contact; docs/registration.md, "Samples spread over the contact"), ``"topk"`` (exact
    top-k of |L| over the contact, method.md 4.2), ``"threshold"`` (the public
    GelSLAM rule) or ``"random"`` (old NormalFlow: random contact pixels, seeded by
    ``seed``). ``check_scores`` False skips the CCS/SCR test (old NormalFlow).
    ``jacobian``: ``"analytic"`` or ``"autograd"`` (torch.func); both agree.
    ``lm_damping`` is a Levenberg-Marquardt factor on the normal equations: it adds
    ``lm_damping * (diag(A) + 1e-3 block mean of diag(A))``, so that it also holds back an
    unobservable direction (``diag(A)`` 0 there). A pair is
    degenerate (failed) when the smallest-to-largest eigenvalue ratio of its normal
    equations, translations scaled by the samples' RMS spread, is below
    ``degenerate_eig`` (0 disables the test). ``coarse_factors`` adds coarse levels
    (e.g. ``(4,)``: normal maps averaged over 4x4 blocks, at most
    ``coarse_max_iters`` iterations each) that widen the basin for large motions.
    ``fallback_factors``: pairs that fail are solved once more from the same start
    through coarse levels of these factors, e.g. ``(16, 4)`` (empty: no retry); only
    failures pay for it. For registration from a poor initial guess; off by default
    because the tracker needs a failure to make a keyframe (docs/registration.md).
    ``fallback_shift_search``: pairs that the fallback does not save are retried once
    more through the same levels, from the start moved to the in-plane shift that best
    aligns the two contacts' normal maps (a global search by FFT cross-correlation, for
    touches millimetres apart; ``registration/shift.py``).
    ``cpu_chunk_samples``: on the CPU a batch of pairs with their own references is
    solved in chunks of ``cpu_chunk_samples // n_samples`` pairs (at least 1), each
    prepared and solved to the end before the next, so that its samples, Jacobians and
    target maps stay in cache across its iterations (0: the whole batch at once). One
    reference for every target, and other devices, always run the whole batch. Results
    do not depend on it beyond rounding.
    ``stall_check_iters``: every this many full-resolution iterations, a pair with a
    failing score (CCS or SCR at its current pose) that would still fail at
    ``max_iters`` if it kept improving at its rate since the previous check stops and is
    reported failed (it is iterating in a wrong basin; without the check it would use the
    rest of ``max_iters`` and still fail). Only with ``check_scores``; 0 disables
    (docs/registration.md, "Stall check").
    ``decoded_max_slope``: a reference frame decoded from an image (``Frame.decoded``)
    takes its samples only from contact pixels no steeper than this (``|n_xy| / |n_z|``),
    unless fewer than a quarter of its contact is that flat. The calibration presses hold
    true slopes up to 0.6, which the shipped model decodes to about 0.5 (gain 0.818);
    steeper decoded slopes are extrapolated and flattened (docs/registration.md, "Steep
    pixels from video"). ``None``: no limit for decoded frames beyond ``max_slope``.
    ``max_slope``: every reference frame, decoded or given as gradients, takes its samples
    only from contact pixels no steeper than this, with the same exception. The gel
    low-passes the indentation in its own frame, and slope is not linear in angle, so on
    steep texture the smoothed slopes of two touches tilted against each other are not
    related by the rotation: NormalFlow from the true pose then stops short of the tilt
    (docs/registration.md, "Steep pixels through the gel"). ``None``: every contact pixel.
    Where both limits apply the lower one holds.
    """

    n_samples: int | None = 3000
    max_iters: int = 50
    min_iters: int = 1
    rot_tol: float = 1e-4
    trans_tol_m: float = 1e-5
    min_shared: int = 10
    ccs_threshold: float = 0.85
    scr_threshold: float = 0.3
    selection: str = "spread"
    sample_cell_px: int = 16
    check_scores: bool = True
    jacobian: str = "analytic"
    lm_damping: float = 0.0
    degenerate_eig: float = 1e-6
    seed: int = 0
    coarse_factors: tuple[int, ...] = ()
    coarse_max_iters: int = 20
    fallback_factors: tuple[int, ...] = ()
    fallback_shift_search: bool = True
    cpu_chunk_samples: int = 48_000
    stall_check_iters: int = 10
    decoded_max_slope: float | None = 0.5
    max_slope: float | None = 0.5

    def check(self, shape: tuple[int, int] | None = None) -> None:
        """Raise :class:`ConfigError` naming the first invalid setting. ``shape`` ``(H, W)``:
        the coarse and fallback factors must also divide the image size."""
        if self.selection not in SAMPLE_SELECTIONS:
            raise ConfigError(f"normalflow.selection must be one of {SAMPLE_SELECTIONS}, got {self.selection!r}")
        for name in ("decoded_max_slope", "max_slope"):
            limit = getattr(self, name)
            if limit is not None and not limit > 0:
                raise ConfigError(f"normalflow.{name} must be > 0 or None, got {limit}")
        if self.sample_cell_px < 1:
            raise ConfigError(f"normalflow.sample_cell_px must be >= 1, got {self.sample_cell_px}")
        if self.jacobian not in JACOBIAN_KINDS:
            raise ConfigError(f"normalflow.jacobian must be one of {JACOBIAN_KINDS}, got {self.jacobian!r}")
        if self.max_iters < 1 or self.min_iters < 1 or self.coarse_max_iters < 1:
            raise ConfigError("normalflow.max_iters, min_iters and coarse_max_iters must be >= 1")
        if self.min_iters > self.max_iters:
            raise ConfigError(f"normalflow.min_iters ({self.min_iters}) must be <= max_iters ({self.max_iters})")
        check_ranges(self, "normalflow")
        if self.n_samples is not None and self.n_samples < self.min_shared:
            raise ConfigError(f"normalflow.n_samples ({self.n_samples}) must be >= normalflow.min_shared "
                              f"({self.min_shared}): with fewer samples every registration fails")
        for name in ("cpu_chunk_samples", "stall_check_iters", "lm_damping"):
            if getattr(self, name) < 0:
                raise ConfigError(f"normalflow.{name} must be >= 0, got {getattr(self, name)}")
        for name in ("coarse_factors", "fallback_factors"):
            for f in getattr(self, name):
                if f < 2 or (shape is not None and (shape[0] % f or shape[1] % f)):
                    raise ConfigError(f"normalflow.{name} must be >= 2 and divide the image size, got {f}")


@dataclass
class TrackingConfig:
    """Tracker thresholds (method.md section 5)."""

    ccs_threshold: float = 0.85
    scr_threshold: float = 0.3
    flush_session_tail: bool = True
    init: str = "constant_position"
    # motion continuity (docs/benchmarks.md, "Motion continuity"): a registration against an older
    # keyframe that implies a faster sensor motion since the previous frame than this is a
    # failure (a slip to a wrong alignment that CCS/SCR cannot see), retried against the
    # previous frame, which accepts real fast motion at the cost of a keyframe; None disables
    max_deg_per_s: float | None = 125.0  # 5 deg per frame at 25 fps
    max_mm_per_s: float | None = 25.0  # 1 mm per frame at 25 fps
    # frames decoded from images (Frame.decoded): a registration against an older keyframe
    # more than this out of plane from it counts as failed, so the lazy rule makes the
    # previous frame a keyframe. The decoder under-reads a tilt by about (1 - gain) of it,
    # and the gain falls to 0.818 at the calibration presses' steepest slopes: 1 deg at
    # 5.5 deg (docs/benchmarks.md, "Keyframes from video"); None: no limit
    decoded_max_tilt_deg: float | None = 5.5
    # every frame (gradients given as input too): the same rule at this tilt. NormalFlow's
    # error grows with the tilt between its frames, and against a keyframe held while the
    # sensor rolls it can stall in a valley of nearly equal alignments with CCS still high
    # (docs/benchmarks.md, "Keyframe tilt limit"); None: no limit
    max_tilt_deg: float | None = 10.0
    # cross-check (docs/benchmarks.md, "Frame-to-frame cross-check where the registration is
    # weak"): a frame is also registered against the previous frame, and a keyframe
    # registration more than this far in rotation from that chained result counts as failed
    # (the lazy rule makes the previous frame a keyframe). Registration against a keyframe
    # held while the sensor rolls over an edge or around a cylinder drifts with CCS still
    # high. 1 deg: the loop benchmark's correctness tolerance, chosen before any run. About
    # 3 ms more per checked frame. None: off
    f2f_check_deg: float | None = 1.0
    # ... only for frames whose keyframe registration is weakly constrained: its
    # `conditioning` (NormalFlow's smallest-to-largest eigenvalue ratio) below this. Rolls
    # and slides along an edge or groove leave a direction nearly free (docs/registration.md,
    # "Degeneracy": 2.5e-3 to 3.4e-3 on a rounded edge, 0.11-0.49 on textured pairs; the
    # class boundary used there is 1e-2). A NaN conditioning is checked. None: every frame
    f2f_below_conditioning: float | None = 1e-2
    # keyframe edges (docs/benchmarks.md, "Keyframe edges"): a new keyframe's pose in the
    # previous one is registered again from starts shifted this far along +-x and +-y, and
    # a start whose result verifies with a CCS higher by more than keyframe_near_margin,
    # within keyframe_near_max_deg / _mm of the tracked pose (one frame's motion limit at
    # 25 fps), replaces it (on ribs a step of about a period slips to the neighbouring
    # rib); where the tracked edge is weakly constrained (below f2f_below_conditioning, with
    # the cross-check on) the frame before the new keyframe must prefer the move by the same
    # margin (on a lattice a period's shift can outscore the truth: "Keyframe edges on a
    # lattice"); None disables
    keyframe_near_mm: float | None = 0.5
    keyframe_near_margin: float = 0.01
    keyframe_near_max_deg: float = 5.0
    keyframe_near_max_mm: float = 1.0
    # while a round moves the edge, search again from the new best (a slip of two ribs),
    # at most this many batches of 5 per keyframe
    keyframe_near_rounds: int = 3
    # contact hysteresis (docs/benchmarks.md, "Contact hysteresis"): a session in progress
    # goes on through frames whose eroded contact area is below the in-contact minimum
    # (contact.min_contact_mm2, 2.0 mm^2) but at least this, while they register; such a
    # frame never starts a session and ends it if it does not register. None: the
    # reference rule (every frame below the minimum ends the session)
    keep_contact_mm2: float | None = 1.0
    # coarse fallback (docs/benchmarks.md, "Coarse fallback"): a frame about to start a new
    # session inside a contact (its registration against the previous frame failed) is
    # registered against it once more through block-averaged levels of these factors and
    # kept if that verifies within the speed limits; 4 widens NormalFlow's basin about 4x,
    # to more than a frame's motion limit (1 mm = 16 px at 25 fps); () disables
    fallback_factors: tuple[int, ...] = (4,)
    # keyframe edge direction (docs/benchmarks.md, "Keyframe edge direction"): a new
    # keyframe's pose in the previous one comes from tracking ("forward", the reference
    # rule), or from registering the previous keyframe against the new one, started from
    # the tracked pose ("reverse"), or the midpoint of the two ("midpoint"); a reverse
    # registration that fails keeps the tracked pose
    keyframe_edge: str = "forward"


@dataclass
class LoopConfig:
    """Loop closure and coverage set (method.md section 6)."""

    ccs_threshold: float = 0.7
    scr_threshold: float = 0.3
    min_sift_inliers: int = 8
    # detection (tactile_slam/loop/detector.py; docs/loops.md)
    mode: str = "full"  # "full" | "only_sift" | "only_nf" | "image_sift" (method.md 9.5)
    sift_backend: str = "opencv"  # "opencv" | "kornia"
    sift_contrast_threshold: float = 0.02
    sift_octave_layers: int = 3
    sift_max_features: int = 512  # kornia backend only
    sift_edge_threshold: float = 10.0  # opencv backend only: keypoints on lines are dropped above it
    # the curvature map SIFT runs on: "laplacian" (method.md 6.2, the public code's) or
    # "gaussian" (the Hessian determinant, which keeps bumps and crossings and drops lines;
    # geometry.curvature): 2-4x the loops between sessions, but not the default yet (it
    # also verifies imprecise loops within a session); docs/loops.md, "Features on the
    # Gaussian curvature"
    feature_map: str = "laplacian"
    ransac_iterations: int = 100
    ransac_threshold_px: float = 3.0
    ransac_confidence: float = 0.99
    ransac_refine_iters: int = 10
    ambiguity_ratio: float | None = 0.5  # reject pairs whose outliers support a 2nd alignment
    max_candidates: int = 10  # keyframes matched per query when more are eligible
    retrieval_neighbours: int = 5
    retrieval_min_votes: int = 3
    retrieval_exact_max: int = 4096  # descriptors searched exactly before a kd-tree is built
    gate_margin_mm: float | None = 2.0  # pose gate within a group; None disables
    max_init_rot_deg: float | None = None  # reject loops whose NF pose leaves the 2-D guess by more
    max_init_trans_mm: float | None = None
    verify_batch: int = 16  # NormalFlow pairs per batch
    # back-end acceptance (tactile_slam/loop/consistency.py; docs/loops.md): a loop within a
    # group that matches the estimate within base + rate * drift path (mm of motion measured
    # by the factors between its ends) is accepted; beyond doubt_factor x that it is rejected;
    # in between, and across groups, it waits until merge_min_pairs agreeing loops come
    # from distinct query keyframes ("queries": separate detections) or from distinct
    # keyframes on both sides ("both": rarely met, the coverage set often leaves one
    # candidate keyframe per region, so sessions did not merge after contact loss);
    # merge_cycles: three single loops between three groups that compose to the identity
    # within the drift tolerance also merge them (short sessions after contact loss)
    consistency: bool = True
    drift_base_rot_deg: float = 3.0
    drift_base_trans_mm: float = 0.5
    drift_rot_deg_per_mm: float = 0.1
    drift_trans_mm_per_mm: float = 0.02
    doubt_factor: float = 5.0
    merge_min_pairs: int = 2
    merge_distinct: str = "queries"
    merge_cycles: bool = True
    # loops on a texture that matches another part of itself (loop.matching.self_similarity)
    # are accepted only within a group where the estimate predicts them, unless trusted
    trust_repetitive: bool = False
    # loops between groups whose pair also verifies from a start half a contact radius away
    # or a quarter/half turn round, at another pose (tactile_slam/loop/ambiguity.py), are
    # held like repetitive ones (trust_repetitive trusts both)
    check_ambiguity: bool = True
    # verified loops move to the verified alignment with the highest CCS among their pose and
    # its shifts by drift_base_trans_mm along +-x and +-y: between groups (with
    # check_ambiguity), and within a group when they differ from the estimate's prediction by
    # more than best_nearby_rot_deg or best_nearby_trans_mm (method.md's release gate for a
    # false loop; 0, 0: every loop); on ribs closer than the gate's tolerance a loop one
    # period off verifies and would pass it (tactile_slam/loop/ambiguity.py, docs/loops.md).
    # Such a loop within a group is also marked ambiguous when another start of
    # ambiguity.starts verifies elsewhere (a lattice coarser than the shifts, e.g. a knurl)
    best_nearby: bool = True
    best_nearby_rot_deg: float = 1.0
    best_nearby_trans_mm: float = 0.3
    # probes (tactile_slam/loop/probe.py): per keyframe, up to this many pairs of groups whose
    # waiting loops come from fewer than merge_min_pairs query keyframes get one predicted
    # keyframe pair verified by NormalFlow, a second query for the gate; joins more sessions
    # on asymmetric objects, confirms false loops on symmetric ones (docs/loops.md); 0: off
    probes: int = 0
    # loops between keyframes decoded from images (Frame.decoded): a decoder that returns a
    # fraction g of a slope under-reads a tilt by about (1 - g) of it (the shipped model's
    # gain on its held-out presses falls to 0.818 at the steepest slopes they hold), so such
    # a loop is the right place at a less certain angle (docs/loops.md, "Tilted loops from
    # video"). It enters the pose graph with this standard deviation on its out-of-plane
    # rotation (about the sensor's x and y axes) instead of posegraph.sigma_rot_rad, and
    # records it as tilt_sigma_deg in loops.json: the shipped model's held-out normal error
    # at those slopes, 5.44 deg (docs/calibration.md, "Gain by slope"). None: weighed like
    # any loop. Translation and the rotation about the sensor axis keep their sigmas.
    decoded_tilt_sigma_deg: float | None = 5.44
    # such loops verified more than this out of plane are held ("tilted" in
    # loops_held.json; checked on the verification's pose, before the back end settles or
    # re-measures the loop): NormalFlow's verification is specified and tested up to 15 deg
    # of tilt (docs/registration.md); None: no limit. Gradients given as input are not limited.
    decoded_max_tilt_deg: float | None = 15.0
    # loops measured both ways (posegraph.refine_both_ways) whose two measurements disagree
    # by more than this rotation or translation are held ("asymmetric" in loops_held.json):
    # one of them is then off by at least half of it, and method.md's release gate allows a
    # loop 1 deg and 0.3 mm (docs/loops.md, "Loops measured both ways"). The out-of-plane
    # part is allowed max(max_asymmetry_deg, tilt_sigma_deg) on loops that declare a tilt
    # sigma (decoded images). None: no limit
    max_asymmetry_deg: float | None = 1.0
    max_asymmetry_mm: float | None = 0.3
    coverage_overlap_mm2: float = 50 * 0.0634**2
    coverage_symmetric: bool = False  # overlap = min of both directions ([Rec] option)
    coverage_depth_gate_mm: float | None = None  # count overlap only within this depth


@dataclass
class PoseGraphConfig:
    """Pose-graph noise and solver (method.md section 7; tactile_slam/posegraph)."""

    sigma_rot_rad: float = 0.01
    sigma_trans_m: float = 1e-4
    max_iters: int = 100
    rel_tol: float = 1e-5
    abs_tol: float = 1e-5
    lambda_init: float = 1e-5
    lambda_factor: float = 10.0
    lambda_max: float = 1e5
    # "none" | "huber" | "cauchy" | "gnc" (truncated least squares), on loop factors only
    robust: str = "none"
    robust_chi2: float = 16.81
    gnc_mu_step: float = 1.4
    gnc_max_iters: int = 100
    reinit_merged: bool = True
    # verified loops re-measured by NormalFlow from their first value over refine_n_samples
    # reference pixels (None: every contact pixel) before the loop gate, except in the
    # only_sift ablation (tactile_slam/registration/refine.py)
    refine_loops: bool = True
    refine_n_samples: int | None = None
    # ... in both directions: also the target's pixels against the reference, the loop's
    # value the midpoint of the two where both pass their checks
    # (registration/refine.py refine_both_ways; loop.max_asymmetry_* holds a loop whose two
    # measurements disagree)
    refine_both_ways: bool = True
    # ... over the pressed core of each keyframe's contact: the pixels that also pass the
    # contact depth test (contact.height_threshold_mm / height_fraction). Image input
    # already has that contact; a looser given mask's rim biases the tilt
    # (docs/registration.md, "Tilt bias at a loose mask's rim")
    refine_core: bool = True
    # incremental updates: first region (poses), boundary test (whitened cost), LM steps per region
    incremental_window: int = 64
    incremental_tol: float = 1e-2
    incremental_max_iters: int = 10


@dataclass
class ReconConfig:
    """Reconstruction (method.md section 8)."""

    fusion_gate_mm: float = 3.0
    poisson: bool = True
    watertight: bool = True  # False: trim Poisson to the data (partial scans)
    min_weight: float = 0.05  # Poisson input: drop points this close to a contact edge
    voxel_mm: float = 0.05
    poisson_cell_mm: float = 0.1
    poisson_min_depth: int = 6  # the 0.1 mm cell rule decides; 8 costs 5x for no gain (docs)
    poisson_max_depth: int = 11
    # Poisson input budget: more voxel-averaged points than this coarsen the voxel and
    # the cell together (bounds meshing time and memory on large scans; docs/reconstruction.md)
    poisson_max_points: int = 500_000
    # Open3D's Poisson threads (-1: every core). Its multi-threaded solver segfaults at
    # random, more often on a busy CPU (isl-org/Open3D#6828, #7229; seen here once in
    # the test suite): one thread by default, so a crash cannot take a run's results.
    poisson_threads: int = 1
    trim_density_quantile: float = 0.02
    trim_distance_mm: float = 0.5
    # also mesh every group besides the main one, each in its own frame (groups/group_<label>/)
    all_groups: bool = False

    def check(self) -> None:
        """Raise :class:`ConfigError` for the rules no single range states (the ranges are
        :data:`_RANGES`): the thread count, and the depth bounds' order."""
        t = self.poisson_threads
        if isinstance(t, bool) or not isinstance(t, int) or not (t == -1 or t >= 1):
            raise ConfigError(f"recon.poisson_threads must be -1 (every core) or an integer >= 1, got {t!r}")
        if self.poisson_max_depth < self.poisson_min_depth:
            raise ConfigError(f"recon.poisson_max_depth must be >= poisson_min_depth, got {self.poisson_max_depth} "
                              f"< {self.poisson_min_depth}")


@dataclass
class Config:
    """Everything tactile-slam needs, one section per concept."""

    sensor: SensorConfig = field(default_factory=SensorConfig)
    contact: ContactConfig = field(default_factory=ContactConfig)
    curvature: CurvatureConfig = field(default_factory=CurvatureConfig)
    normalflow: NormalFlowConfig = field(default_factory=NormalFlowConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    loop: LoopConfig = field(default_factory=LoopConfig)
    posegraph: PoseGraphConfig = field(default_factory=PoseGraphConfig)
    recon: ReconConfig = field(default_factory=ReconConfig)

    # ------------------------------------------------------------------ derived
    @property
    def min_contact_px(self) -> float:
        return self.sensor.px_from_mm2(self.contact.min_contact_mm2)

    @property
    def final_erode_px(self) -> int:
        if self.contact.final_erode is not None:
            return self.contact.final_erode
        return max(self.sensor.height // 48, 1)

    @property
    def height_threshold_px(self) -> float:
        return self.contact.height_threshold_mm / self.sensor.mm_per_px

    @property
    def depth_test(self) -> tuple[float, float | None, float]:
        """``(threshold_px, fraction, floor_px)`` of the contact depth test for
        :func:`tactile_slam.geometry.contact.contact_mask`."""
        c = self.contact
        if c.height_fraction is not None and not 0.0 < c.height_fraction <= 1.0:
            raise ConfigError(f"contact.height_fraction must be in (0, 1] or None, got {c.height_fraction}")
        if not 0.0 <= c.min_depth_mm < float("inf"):
            raise ConfigError(f"contact.min_depth_mm must be a finite number >= 0, got {c.min_depth_mm}")
        return self.height_threshold_px, c.height_fraction, c.min_depth_mm / self.sensor.mm_per_px

    # ------------------------------------------------------------------ I/O
    def to_dict(self) -> dict[str, Any]:
        """Plain YAML-ready values (tuples become lists)."""
        return dataclasses.asdict(
            self, dict_factory=lambda kv: {k: list(v) if isinstance(v, tuple) else v for k, v in kv})

    def save(self, path: str | Path) -> None:
        Path(path).write_text(yaml.dump(self.to_dict(), Dumper=_YamlDumper, sort_keys=False))

    @classmethod
    def from_dict(cls, data: dict[str, Any], base_dir: Path | None = None) -> "Config":
        if not isinstance(data, dict):
            raise ConfigError(f"config must be a mapping, got {type(data).__name__}")
        if any(k in data for k in ("device_config", "contact_mask_config", "gelslam_config")):
            data = _from_gelslam_layout(data)
        sensor = data.get("sensor")
        if isinstance(sensor, dict) and "ppmm" in sensor:  # GelSLAM's name for mm_per_px, also in our layout
            if "mm_per_px" in sensor:
                raise ConfigError("sensor.ppmm and sensor.mm_per_px are the same setting: give one")
            data = {**data, "sensor": {("mm_per_px" if k == "ppmm" else k): v for k, v in sensor.items()}}
        cfg = cls()
        for name, section in data.items():
            if not hasattr(cfg, name) or not dataclasses.is_dataclass(getattr(cfg, name)):
                raise ConfigError(f"unknown config section {name!r}")
            if section is None:
                continue
            setattr(cfg, name, _update(getattr(cfg, name), section, name))
        if base_dir is not None and cfg.sensor.model_path is not None:
            p = Path(cfg.sensor.model_path)
            if not p.is_absolute():
                cfg.sensor.model_path = str((base_dir / p).resolve())
        cfg.validate()
        return cfg

    @classmethod
    def from_yaml(cls, path: str | Path) -> "Config":
        path = Path(path)
        if not path.is_file():
            raise ConfigError(f"config file not found: {path}")
        try:
            data = yaml.load(path.read_text(), Loader=_YamlLoader) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"config file {path} is not valid YAML: {exc}") from exc
        return cls.from_dict(data, base_dir=path.parent)

    def validate(self) -> None:
        s = self.sensor
        if not s.mm_per_px > 0:
            raise ConfigError(f"sensor.mm_per_px must be > 0, got {s.mm_per_px}")
        if s.width <= 0 or s.height <= 0:
            raise ConfigError(f"sensor size must be positive, got {s.width}x{s.height}")
        if s.fps <= 0:
            raise ConfigError(f"sensor.fps must be > 0, got {s.fps}")
        if s.background_frames < 1:
            raise ConfigError("sensor.background_frames must be >= 1")
        if self.curvature.blur_ksize % 2 != 1:
            raise ConfigError("curvature.blur_ksize must be odd")
        if min(s.width, s.height) < min_image_px(self.curvature.blur_ksize):
            raise ConfigError(f"sensor size {s.width}x{s.height} is too small for the curvature blur "
                              f"(curvature.blur_ksize {self.curvature.blur_ksize}: at least "
                              f"{min_image_px(self.curvature.blur_ksize)} px each way)")
        for key, values in _CHOICES:
            section, name = key.split(".")
            value = getattr(getattr(self, section), name)
            if value not in values:
                raise ConfigError(f"{key} must be one of {values}, got {value!r}")
        self.normalflow.check()  # the factors are checked against the frames' size when they register
        for section in ("contact", "curvature", "tracking", "loop", "posegraph", "recon"):
            check_ranges(getattr(self, section), section)
        for key in FACTOR_KEYS:
            section, name = key.split(".")
            if any(f < 2 for f in getattr(getattr(self, section), name)):
                raise ConfigError(f"{key} must be integers >= 2, got {list(getattr(getattr(self, section), name))}")
        self.recon.check()

    def check_factors(self) -> None:
        """Raise :class:`ConfigError` unless every block-averaging factor
        (:data:`FACTOR_KEYS`) divides the sensor size; the pipelines check this before
        tracking (calibration, which never tracks, needs no such size)."""
        s = self.sensor
        for key in FACTOR_KEYS:
            section, name = key.split(".")
            bad = [f for f in getattr(getattr(self, section), name) if s.width % f or s.height % f]
            if bad:
                raise ConfigError(f"{key} must divide the sensor size {s.width}x{s.height}, got {bad[0]} "
                                  f"(an empty list, {key}: [], turns those levels off)")


class _YamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads exponents without a dot (``1e-5``) as floats,
    as YAML 1.2 does; PyYAML's YAML 1.1 rules read them as strings."""


class _YamlDumper(yaml.SafeDumper):
    """PyYAML's safe dumper that quotes strings :class:`_YamlLoader` would read as floats
    (a sensor named ``3E8``), so a saved config loads back as it was."""


for _cls in (_YamlLoader, _YamlDumper):
    _cls.add_implicit_resolver("tag:yaml.org,2002:float", re.compile(r"^[-+]?[0-9][0-9_]*(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
                               list("-+0123456789"))


def _rule(low: float | None = None, high: float | None = None, open_low: bool = False,
          open_high: bool = False) -> tuple:
    """A range test and its wording for :data:`_RANGES`."""
    def ok(v) -> bool:
        return ((low is None or (v > low if open_low else v >= low))
                and (high is None or (v < high if open_high else v <= high)))
    if high is None:
        return ok, f"{'>' if open_low else '>='} {low}"
    return ok, f"in {'(' if open_low else '['}{low}, {high}{')' if open_high else ']'}"


_NON_NEGATIVE, _POSITIVE, _AT_LEAST_ONE, _UNIT = _rule(0), _rule(0, open_low=True), _rule(1), _rule(0, 1)
_RANGES = tuple((key, *rule) for key, rule in (
    ("contact.color_dist_threshold", _NON_NEGATIVE), ("contact.dilate", _NON_NEGATIVE),
    ("contact.erode", _NON_NEGATIVE), ("contact.height_threshold_mm", _NON_NEGATIVE),
    ("contact.height_percentile", _rule(0, 100)), ("contact.final_erode", _NON_NEGATIVE),
    ("contact.min_contact_mm2", _NON_NEGATIVE), ("contact.mlp_skip_color_dist", _NON_NEGATIVE),
    ("curvature.blur_ksize", _AT_LEAST_ONE), ("curvature.blur_sigma", _POSITIVE), ("curvature.clip", _POSITIVE),
    ("normalflow.n_samples", _AT_LEAST_ONE), ("normalflow.min_shared", _AT_LEAST_ONE),
    ("normalflow.ccs_threshold", _UNIT), ("normalflow.scr_threshold", _UNIT),
    ("normalflow.rot_tol", _NON_NEGATIVE), ("normalflow.trans_tol_m", _NON_NEGATIVE),
    ("normalflow.degenerate_eig", _NON_NEGATIVE),
    ("tracking.ccs_threshold", _UNIT), ("tracking.scr_threshold", _UNIT),
    ("loop.ccs_threshold", _UNIT), ("loop.scr_threshold", _UNIT), ("loop.ransac_iterations", _AT_LEAST_ONE),
    ("loop.ransac_threshold_px", _POSITIVE), ("loop.ransac_confidence", _rule(0, 1, True, True)),
    ("loop.coverage_overlap_mm2", _NON_NEGATIVE), ("loop.sift_octave_layers", _AT_LEAST_ONE),
    ("loop.sift_contrast_threshold", _NON_NEGATIVE), ("loop.sift_max_features", _AT_LEAST_ONE),
    ("loop.ransac_refine_iters", _NON_NEGATIVE), ("loop.ambiguity_ratio", _POSITIVE),
    ("loop.gate_margin_mm", _NON_NEGATIVE), ("loop.max_init_rot_deg", _NON_NEGATIVE),
    ("loop.max_init_trans_mm", _NON_NEGATIVE), ("loop.coverage_depth_gate_mm", _POSITIVE),
    ("loop.retrieval_neighbours", _AT_LEAST_ONE), ("loop.retrieval_min_votes", _AT_LEAST_ONE),
    ("loop.retrieval_exact_max", _NON_NEGATIVE), ("loop.drift_base_rot_deg", _NON_NEGATIVE),
    ("loop.drift_base_trans_mm", _NON_NEGATIVE), ("loop.drift_rot_deg_per_mm", _NON_NEGATIVE),
    ("loop.drift_trans_mm_per_mm", _NON_NEGATIVE), ("loop.doubt_factor", _rule(1)),
    ("loop.merge_min_pairs", _AT_LEAST_ONE), ("loop.decoded_tilt_sigma_deg", _POSITIVE),
    ("loop.decoded_max_tilt_deg", _POSITIVE), ("loop.max_asymmetry_deg", _NON_NEGATIVE),
    ("loop.max_asymmetry_mm", _NON_NEGATIVE), ("loop.probes", _NON_NEGATIVE),
    ("posegraph.sigma_rot_rad", _POSITIVE), ("posegraph.sigma_trans_m", _POSITIVE),
    ("posegraph.max_iters", _AT_LEAST_ONE), ("posegraph.rel_tol", _NON_NEGATIVE),
    ("posegraph.abs_tol", _NON_NEGATIVE), ("posegraph.lambda_init", _POSITIVE),
    ("posegraph.lambda_factor", _rule(1, open_low=True)), ("posegraph.lambda_max", _POSITIVE),
    ("posegraph.robust_chi2", _POSITIVE), ("posegraph.gnc_mu_step", _rule(1, open_low=True)),
    ("posegraph.gnc_max_iters", _AT_LEAST_ONE), ("posegraph.incremental_window", _AT_LEAST_ONE),
    ("posegraph.incremental_tol", _NON_NEGATIVE), ("posegraph.incremental_max_iters", _AT_LEAST_ONE),
    ("recon.fusion_gate_mm", _POSITIVE), ("recon.voxel_mm", _POSITIVE), ("recon.poisson_cell_mm", _POSITIVE),
    ("recon.poisson_min_depth", _rule(1, 16)), ("recon.poisson_max_depth", _rule(1, 16)),
    ("recon.poisson_max_points", _AT_LEAST_ONE), ("recon.trim_density_quantile", _rule(0, 1, open_high=True)),
    ("recon.trim_distance_mm", _NON_NEGATIVE), ("recon.min_weight", _rule(0, 1, open_high=True)),
))
"""Ranges checked at load (:meth:`Config.validate`; the ``normalflow`` ones also by
:meth:`NormalFlowConfig.check`, which registration calls), ``None`` values exempt: settings
no constructor checks before the frames are read (the tracker's and the loop detector's
own checks run when a pipeline is built; these would otherwise fail late, e.g. meshing
after the whole run, or not at all). NaN fails every range."""

_CHOICES = (
    ("contact.given_masks", GIVEN_MASKS), ("tracking.init", TRACKING_INITS),
    ("tracking.keyframe_edge", KEYFRAME_EDGES), ("loop.mode", LOOP_DETECTOR_MODES),
    ("loop.feature_map", FEATURE_MAPS), ("loop.sift_backend", SIFT_BACKENDS),
    ("loop.merge_distinct", MERGE_DISTINCT), ("posegraph.robust", ROBUST_MODES),
)
"""String settings and their allowed values, checked at load (:meth:`Config.validate`;
``normalflow``'s by :meth:`NormalFlowConfig.check`)."""


_RANGES_BY_SECTION: dict[str, list[tuple[str, str, Any, str]]] = {}
for _key, _ok, _text in _RANGES:
    _RANGES_BY_SECTION.setdefault(_key.split(".")[0], []).append((_key, _key.split(".")[1], _ok, _text))


def check_ranges(settings: Any, section: str) -> None:
    """Raise :class:`ConfigError` naming the first setting of ``section`` (a config
    dataclass) outside its range in :data:`_RANGES`."""
    for key, name, rule, text in _RANGES_BY_SECTION.get(section, ()):
        value = getattr(settings, name)
        if value is not None and not rule(value):
            raise ConfigError(f"{key} must be {text}, got {value!r}")


def _update(obj: Any, values: dict[str, Any], section: str) -> Any:
    if not isinstance(values, dict):
        raise ConfigError(f"config section {section!r} must be a mapping")
    known = {f.name: f for f in dataclasses.fields(obj)}
    hints = typing.get_type_hints(type(obj))
    kwargs = {}
    for key, value in values.items():
        if key not in known:
            raise ConfigError(f"unknown key {section}.{key}")
        kwargs[key] = _typed(value, hints[key], f"{section}.{key}")
    return dataclasses.replace(obj, **kwargs)


def _typed(value: Any, hint: Any, where: str) -> Any:
    """``value`` checked against a field's annotation (``bool``, ``int``, ``float``,
    ``str``, ``X | None``, ``tuple[int, ...]``); ints are accepted for floats and lists
    for tuples; floats must be finite. Raises :class:`ConfigError` naming the key otherwise."""
    args = typing.get_args(hint)
    if type(None) in args:
        if value is None:
            return None
        (hint,) = [a for a in args if a is not type(None)]
    if typing.get_origin(hint) is tuple:
        if isinstance(value, (list, tuple)):
            item = typing.get_args(hint)[0]  # tuple[X, ...]
            return tuple(_typed(v, item, f"{where}[{i}]") for i, v in enumerate(value))
        raise ConfigError(f"{where} must be a list, got {value!r}")
    if hint is bool and isinstance(value, bool):
        return value
    if hint is int and isinstance(value, int) and not isinstance(value, bool):
        return value
    if hint is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        if not math.isfinite(value):  # YAML's .nan / .inf: no setting means "unbounded" that way
            raise ConfigError(f"{where} must be a finite number, got {value!r}")
        return float(value)
    if hint is str and isinstance(value, str):
        return value
    name = getattr(hint, "__name__", str(hint))
    raise ConfigError(f"{where} must be of type {name}{' or null' if type(None) in args else ''}, got {value!r}")


def _from_gelslam_layout(data: dict[str, Any]) -> dict[str, Any]:
    """Translate the public GelSLAM config.yaml layout into this project's sections."""
    for k in data:
        if k not in ("device_config", "contact_mask_config", "gelslam_config"):
            raise ConfigError(f"unknown config section {k!r} in GelSLAM layout")
    out: dict[str, dict[str, Any]] = {"sensor": {}, "contact": {}, "tracking": {}, "loop": {}}
    dev = _gelslam_section(data, "device_config")
    mapping = {
        "device_name": "name",
        "ppmm": "mm_per_px",  # misnamed upstream: it is millimetres per pixel
        "imgh": "height",
        "imgw": "width",
        "raw_imgh": "raw_height",
        "raw_imgw": "raw_width",
        "framerate": "fps",
        "calibration_model_path": "model_path",
    }
    for k, v in dev.items():
        if k not in mapping:
            raise ConfigError(f"unknown key device_config.{k}")
        out["sensor"][mapping[k]] = v
    mm_per_px = (_gelslam_number(dev["ppmm"], "device_config.ppmm") if "ppmm" in dev
                 else SensorConfig.mm_per_px)
    cm = _gelslam_section(data, "contact_mask_config")
    for k, v in cm.items():
        if k == "color_dist_threshold":
            out["contact"]["color_dist_threshold"] = v
        elif k == "height_threshold":
            out["contact"]["height_threshold_mm"] = v
        else:
            raise ConfigError(f"unknown key contact_mask_config.{k}")
    gs = _gelslam_section(data, "gelslam_config")
    for k in gs:
        if k not in ("track_config", "pose_graph_config"):
            raise ConfigError(f"unknown key gelslam_config.{k}")
    for k, v in _gelslam_section(gs, "track_config", "gelslam_config.").items():
        if k == "contact_threshold":  # pixels upstream; stored as an area here
            out["contact"]["min_contact_mm2"] = _gelslam_number(v, f"gelslam_config.track_config.{k}") * mm_per_px**2
        elif k in ("scr_threshold", "ccs_threshold"):
            out["tracking"][k] = v
        else:
            raise ConfigError(f"unknown key gelslam_config.track_config.{k}")
    for k, v in _gelslam_section(gs, "pose_graph_config", "gelslam_config.").items():
        if k == "coverage_graph_overlap_threshold":
            out["loop"]["coverage_overlap_mm2"] = (
                _gelslam_number(v, f"gelslam_config.pose_graph_config.{k}") * mm_per_px**2)
        elif k in ("scr_threshold", "ccs_threshold", "min_sift_inliers"):
            out["loop"][k] = v
        else:
            raise ConfigError(f"unknown key gelslam_config.pose_graph_config.{k}")
    return out


def _gelslam_section(data: dict[str, Any], name: str, prefix: str = "") -> dict[str, Any]:
    """``data[name]`` as a mapping (``{}`` when absent or empty); :class:`ConfigError` naming it otherwise."""
    section = data.get(name) or {}
    if not isinstance(section, dict):
        raise ConfigError(f"{prefix}{name} must be a mapping, got {section!r}")
    return section


def _gelslam_number(value: Any, where: str) -> float:
    """A GelSLAM setting that is converted before typing (``ppmm``, pixel counts) as a
    finite float; :class:`ConfigError` naming the key otherwise."""
    return _typed(value, float, where)


def gelsight_mini() -> Config:
    """Preset: GelSight Mini, 0.0634 mm/px, 320x240 at 25 fps, raw 3280x2464."""
    return Config()


def digit() -> Config:
    """Preset: DIGIT, 0.0405 mm/px, raw 640x480 at 60 fps, worked at 320x240.

    The 0.0405 mm/px scale is the public code's value for the working image.
    """
    cfg = Config()
    cfg.sensor = SensorConfig(
        name="DIGIT", mm_per_px=0.0405, width=320, height=240, raw_width=640,
        raw_height=480, fps=60.0,
    )
    return cfg


PRESETS = {"gelsight_mini": gelsight_mini, "digit": digit}


def load_config(source: str | Path | None = None) -> Config:
    """A preset name (``gelsight_mini``, ``digit``), a YAML path, or ``None`` (Mini)."""
    if source is None:
        return gelsight_mini()
    if str(source) in PRESETS:
        return PRESETS[str(source)]()
    return Config.from_yaml(source)
