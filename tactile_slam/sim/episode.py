"""Synthetic episodes on disk: the layout of a recorded scan plus ground truth.

An episode folder holds (``T`` frames, ``H x W`` pixels; docs/simulator.md):

* ``gelsight.avi``: lossless FFV1 BGR video at the sensor's frame rate, read back
  bit-exactly; its first ``lead_in`` (10) frames are contact-free. Image level only.
* ``background.png``: the noise-free background the images were made on. Image level only.
* ``gt_poses.npy``: ``(T, 4, 4)`` float64 ``object_T_sensor``, the sensor pose in the
  object frame, metres, for every video frame.
* ``in_contact.npy``: ``(T,)`` bool, rendered contact area at least the in-contact minimum.
* ``gt_gradients.npz``: ``gradients`` ``(T, H, W, 2)`` float16 and ``contact``
  ``(T, H, W)`` bool (deflate-compressed, written while rendering).
* ``object.ply``: the object mesh in metres, in the object frame.
* ``meta.yaml``: sensor, object, kind, seed, level, gel and motion settings, and the
  ground-truth motion range.

The image level needs the forward colour model (``models/gelsight_mini_colour.pt``
from the calibration step, see :class:`tactile_slam.calibration.colour_model.ColourModel`);
the gradient level needs nothing and writes everything but the video and background.
"""

from __future__ import annotations

import dataclasses
import math
import warnings
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import open3d as o3d
import torch
import yaml

from tactile_slam.config import GELSIGHT_MINI_ENV, MODELS_DIR, Config, gelsight_mini_data
from tactile_slam.eval.tracking_metrics import frame_steps, motion_range
from tactile_slam.eval.trajectory import relative_to
from tactile_slam.io.gradients import EPISODE_NPZ
from tactile_slam.io.scan import VIDEO_NAME
from tactile_slam.sim.motions import MOTION_REVISION, Motion, MotionConfig, make_motion
from tactile_slam.sim.objects import OBJECTS, extent_mm, resolve_object
from tactile_slam.sim.renderer import GelRenderer, RenderConfig

LEVELS = ("gradients", "image")
VIDEO, BACKGROUND, POSES, CONTACT, GRADIENTS, MESH, META = (
    VIDEO_NAME, "background.png", "gt_poses.npy", "in_contact.npy", EPISODE_NPZ, "object.ply", "meta.yaml")
DEFAULT_COLOUR_MODEL = MODELS_DIR / "gelsight_mini_colour.pt"


class EpisodeError(ValueError):
    """An episode folder is missing files or holds inconsistent data."""


class ImplausibleMotionWarning(UserWarning):
    """The simulated motion moves faster in some frame than the tracker accepts as a hand's
    motion (``tracking.max_deg_per_s`` / ``max_mm_per_s``): on a very irregular or
    non-convex mesh the contact path can jump across a concavity."""


def motion_steps(poses: np.ndarray, in_contact: np.ndarray, config: Config) -> dict:
    """The largest step between consecutive in-contact frames and how many steps exceed
    the tracker's motion limits at the sensor's frame rate (a limit that is ``None``
    counts nothing). JSON/YAML-ready."""
    deg, mm = frame_steps(poses, in_contact)
    fps, tc = config.sensor.fps, config.tracking
    lim_deg = None if tc.max_deg_per_s is None else tc.max_deg_per_s / fps
    lim_mm = None if tc.max_mm_per_s is None else tc.max_mm_per_s / fps
    over = np.zeros(len(deg), bool)
    with np.errstate(invalid="ignore"):
        if lim_deg is not None:
            over |= deg > lim_deg
        if lim_mm is not None:
            over |= mm > lim_mm
    finite = np.isfinite(deg)
    return {"max_deg_per_frame": float(deg[finite].max()) if finite.any() else 0.0,
            "max_mm_per_frame": float(mm[finite].max()) if finite.any() else 0.0,
            "limit_deg_per_frame": lim_deg, "limit_mm_per_frame": lim_mm,
            "steps_over_limit": int(over.sum()),
            "first_step_over_limit": int(np.argmax(over)) if over.any() else None}


class SyntheticBackgroundWarning(UserWarning):
    """Images are composed on the synthetic background: the real one was not found. The
    shipped decoder was trained on the real sensor's images, so image-level results then
    measure a sensor it was not calibrated for."""


# ---------------------------------------------------------------- image formation


def synthetic_background(shape: tuple[int, int]) -> np.ndarray:
    """A smooth GelSight-like background ``(H, W, 3)`` uint8: a mean colour near a
    GelSight Mini's (B, G, R ~ 105, 95, 78) with smooth left-right and top-bottom colour
    gradients and a vignette. Used when no real background is available."""
    h, w = shape
    y, x = np.meshgrid(np.linspace(-1, 1, h), np.linspace(-1, 1, w), indexing="ij")
    vignette = 1.0 - 0.12 * (x**2 + y**2)
    bgr = np.stack([105 - 20 * x + 6 * y, 95 + 8 * y - 4 * x, 78 + 25 * x - 10 * y], -1) * vignette[..., None]
    return np.clip(np.round(bgr), 0, 255).astype(np.uint8)


def background_source(path: str | Path | None = None) -> str:
    """Which background :func:`load_background_image` composes on, without reading it:
    ``path``; else the real GelSight Mini background (``calibration/background.png`` under
    :func:`~tactile_slam.config.gelsight_mini_data`) when present; else ``"synthetic"``."""
    if path is not None:
        return str(path)
    real = gelsight_mini_data() / "calibration" / "background.png"
    return str(real) if real.is_file() else "synthetic"


def load_background_image(path: str | Path | None, shape: tuple[int, int]) -> tuple[np.ndarray, str]:
    """``(background (H, W, 3) uint8, source)`` of :func:`background_source`; the synthetic
    one (:func:`synthetic_background`) with a :class:`SyntheticBackgroundWarning`."""
    source = background_source(path)
    if source == "synthetic":
        warnings.warn(f"no background at {gelsight_mini_data() / 'calibration' / 'background.png'} (set "
                      f"${GELSIGHT_MINI_ENV} to the GelSight Mini data folder): images are composed on a synthetic "
                      "background that the shipped decoder was not calibrated on", SyntheticBackgroundWarning,
                      stacklevel=2)
        return synthetic_background(shape), source
    path = source
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise EpisodeError(f"cannot read background image {path}")
    if img.shape[:2] != tuple(shape):
        raise EpisodeError(f"background {path} is {img.shape[1]}x{img.shape[0]}, expected {shape[1]}x{shape[0]}")
    return img, str(path)


def load_colour_model(path: str | Path | None = None, device: torch.device | str = "cpu"):
    """The calibration step's forward colour model (``gradients -> BGR - background``).

    Raises:
        EpisodeError: the model file does not exist yet (fit it with the calibration
            CLI, or simulate at ``--level gradients``).
    """
    from tactile_slam.calibration.colour_model import ColourModel

    path = Path(path) if path is not None else DEFAULT_COLOUR_MODEL
    if not path.is_file():
        raise EpisodeError(
            f"image-level simulation needs a forward colour model, not found at {path}; fit one with the "
            "calibration tools or simulate at the gradient level (--level gradients)"
        )
    return ColourModel.load(path, device)


def compose_images(gradients: torch.Tensor, background: np.ndarray, colour_model, noise_std: float,
                   seed: int, first_index: int) -> np.ndarray:
    """BGR frames = background + colour_model(gradients) + Gaussian noise, rounded.

    Args:
        gradients: ``(N, H, W, 2)`` slopes.
        background: ``(H, W, 3)`` uint8.
        colour_model: callable ``(N, H, W, 2) -> (N, H, W, 3)`` BGR difference.
        noise_std: sensor noise in grey levels.
        seed, first_index: frame ``k`` of the batch draws its noise from
            ``default_rng([seed, first_index + k])``, so images do not depend on batching.

    Returns:
        ``(N, H, W, 3)`` uint8.
    """
    diff = colour_model(gradients).detach().cpu().numpy().astype(np.float64)
    out = background[None].astype(np.float64) + diff
    if noise_std > 0:
        for k in range(len(out)):
            out[k] += np.random.default_rng([seed, first_index + k]).normal(0.0, noise_std, out[k].shape)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


# ---------------------------------------------------------------- npz streaming


class _NpyMember:
    """Writes one ``.npy`` member of a zip archive chunk by chunk."""

    def __init__(self, archive: zipfile.ZipFile, name: str, shape: tuple[int, ...], dtype: np.dtype):
        self.fp = archive.open(name + ".npy", "w", force_zip64=True)
        header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)), "fortran_order": False, "shape": shape}
        np.lib.format.write_array_header_2_0(self.fp, header)
        self.dtype = np.dtype(dtype)

    def write(self, chunk: np.ndarray) -> None:
        self.fp.write(np.ascontiguousarray(chunk, dtype=self.dtype).tobytes())

    def close(self) -> None:
        self.fp.close()


# ---------------------------------------------------------------- writing


@dataclass
class SimulationSettings:
    """What to simulate (lengths in mm at this user-facing edge).

    Attributes:
        object: catalogue name (:data:`tactile_slam.sim.objects.OBJECTS`) or mesh path.
        kind: ``tracking``, ``contact_loss``, ``scan`` or ``long``.
        seed: seeds the object texture, the motion and the image noise.
        frames: number of frames; ``None`` = the kind's default.
        level: ``gradients`` or ``image``.
        size_mm: catalogue object size; ``None`` = the catalogue default. Refused for a
            mesh file.
        mesh_scale: scale from a user mesh's units to metres; ``None`` = 1 (metres).
            Refused for a catalogue object.
        noise_std: image noise (grey levels).
        colour_model: forward colour model file (``None``: the packaged default).
        background: background image (``None``: real Mini background if present, else synthetic).
        batch: frames rendered at a time.
    """

    object: str = "seed"
    kind: str = "tracking"
    seed: int = 0
    frames: int | None = None
    level: str = "gradients"
    size_mm: float | None = None
    mesh_scale: float | None = None
    noise_std: float = 1.0
    colour_model: str | None = None
    background: str | None = None
    batch: int = 32


def simulate_episode(out_dir: str | Path, settings: SimulationSettings, config: Config | None = None,
                     render_config: RenderConfig | None = None, motion_config: MotionConfig | None = None,
                     device: torch.device | str = "cpu") -> Path:
    """Render an episode into ``out_dir`` (created; existing episode files are replaced).

    Returns:
        ``out_dir``.

    Raises:
        EpisodeError: a bad setting (before rendering), or no frame of the rendered
            episode is in contact (the object too small for the sensor, or a mesh in other
            units); then nothing is written and ``out_dir`` is left as it was.
        ObjectError: an unknown object, or a size for a mesh file or a mesh scale for a
            catalogue object.
    """
    if settings.level not in LEVELS:
        raise EpisodeError(f"level must be one of {LEVELS}, got {settings.level!r}")
    if not (math.isfinite(settings.noise_std) and settings.noise_std >= 0):
        raise EpisodeError(f"image noise must be a finite std >= 0 grey levels, got {settings.noise_std}")
    if settings.mesh_scale is not None and not (math.isfinite(settings.mesh_scale) and settings.mesh_scale > 0):
        raise EpisodeError(f"mesh scale must be finite and > 0, got {settings.mesh_scale}")
    if settings.batch < 1:
        raise EpisodeError(f"batch must be >= 1 frame, got {settings.batch}")
    config = config or Config()
    motion_config = motion_config or MotionConfig()
    colour_model = background = None
    background_source = None
    if settings.level == "image":  # fail before rendering if the colour model is missing
        colour_model = load_colour_model(settings.colour_model, device)
        background, background_source = load_background_image(settings.background, config.sensor.shape)
    mesh = resolve_object(settings.object, settings.size_mm, settings.seed, settings.mesh_scale)
    renderer = GelRenderer(mesh, config, render_config, device)
    motion = make_motion(renderer, settings.kind, settings.frames, settings.seed, motion_config)
    out = Path(out_dir)
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    in_contact = _render_to_disk(out, renderer, motion, settings, colour_model, background)
    rendered = [out / GRADIENTS] + ([out / VIDEO] if colour_model is not None else [])
    if not in_contact.any():
        for path in rendered:
            _staged(path).unlink()
        if created:
            out.rmdir()
        raise EpisodeError(no_contact_message(settings, mesh, config, len(in_contact)))
    for path in rendered:
        _staged(path).replace(path)
    np.save(out / POSES, motion.object_T_sensor)
    np.save(out / CONTACT, in_contact)
    o3d.io.write_triangle_mesh(str(out / MESH), mesh)
    if background is not None:
        cv2.imwrite(str(out / BACKGROUND), background)
    first = int(np.argmax(in_contact))
    gt_rel = relative_to(motion.object_T_sensor, first)
    steps = motion_steps(motion.object_T_sensor, in_contact, config)
    if steps["steps_over_limit"]:
        warnings.warn(f"{settings.object}: {steps['steps_over_limit']} simulated frame steps move faster than the "
                      f"tracker accepts (up to {steps['max_deg_per_frame']:.1f} deg and "
                      f"{steps['max_mm_per_frame']:.2f} mm in one frame, first after frame "
                      f"{steps['first_step_over_limit']}; limits {steps['limit_deg_per_frame']} deg, "
                      f"{steps['limit_mm_per_frame']} mm): the contact path jumps on this surface, and the tracker "
                      "will refuse those steps (meta.yaml motion_steps)", ImplausibleMotionWarning, stacklevel=2)
    meta = {
        "format": "tactile-slam-episode",
        "version": 1,
        "kind": settings.kind,
        "level": settings.level,
        "seed": settings.seed,
        "frames": int(len(motion.object_T_sensor)),
        "lead_in": motion_config.lead_in,
        "first_contact_frame": first,
        "contact_frames": int(in_contact.sum()),
        "pose_convention": "gt_poses[i] = object_T_sensor (sensor pose in the object frame), metres",
        "sensor": dataclasses.asdict(config.sensor),
        "object": {"name": settings.object, "catalogue": settings.object in OBJECTS, **applied_size(settings),
                   "extent_mm": extent_mm(mesh), "triangles": len(mesh.triangles), "file": MESH},
        "gel": dataclasses.asdict(renderer.render_config),
        "motion": _plain(dataclasses.asdict(motion_config)),
        "motion_revision": MOTION_REVISION,
        "motion_paths": {"paths": motion.paths, "replanned": motion.replanned},
        "motion_range_from_first_contact": motion_range(gt_rel[first:], in_contact[first:]),
        "motion_steps": steps,
        "image": None if settings.level == "gradients" else {
            "colour_model": str(settings.colour_model or DEFAULT_COLOUR_MODEL),
            "background": background_source, "noise_std": settings.noise_std},
    }
    (out / META).write_text(yaml.safe_dump(meta, sort_keys=False))
    return out


def applied_size(settings: SimulationSettings) -> dict:
    """``{"size_mm", "mesh_scale"}`` as applied to the object (``meta.yaml``): a catalogue
    object's size (the default when none was given) and no scale; a mesh file's scale
    (1 when none was given) and no size."""
    if settings.object in OBJECTS:
        size = OBJECTS[settings.object].default_size_mm if settings.size_mm is None else float(settings.size_mm)
        return {"size_mm": size, "mesh_scale": None}
    return {"size_mm": None, "mesh_scale": 1.0 if settings.mesh_scale is None else float(settings.mesh_scale)}


def no_contact_message(settings: SimulationSettings, mesh: o3d.geometry.TriangleMesh, config: Config,
                       frames: int) -> str:
    """Why an episode with no frame in contact is refused, with the object's size."""
    return (f"{settings.object}: no frame of the {frames}-frame {settings.kind} episode is in contact (a contact area "
            f"of at least {config.contact.min_contact_mm2:.2f} mm^2 is needed); the object is "
            f"{extent_mm(mesh):.4g} mm across: too small for the sensor, or a mesh file in other units "
            "(--mesh-scale)")


def _staged(path: Path) -> Path:
    """The temporary name a rendered file is written under until the episode is accepted."""
    return path.with_name(f"{path.stem}.part{path.suffix}")


def _plain(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _render_to_disk(out: Path, renderer: GelRenderer, motion: Motion, settings: SimulationSettings,
                    colour_model, background) -> np.ndarray:
    """Render in batches, streaming gradients into the npz and frames into the video, both
    under their :func:`_staged` names; ``(T,)`` bool in-contact flags."""
    poses = motion.object_T_sensor
    t = len(poses)
    h, w = renderer.config.sensor.shape
    in_contact = np.zeros(t, dtype=bool)
    contact_bits = []
    tmp = _staged(out / GRADIENTS)

    def frames() -> Iterator[np.ndarray]:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
            member = _NpyMember(zf, "gradients", (t, h, w, 2), np.float16)
            for a in range(0, t, settings.batch):
                maps = renderer.render(poses[a:a + settings.batch])
                member.write(maps.gradients.cpu().numpy().astype(np.float16))
                contact = maps.contact.cpu().numpy()
                contact_bits.append(np.packbits(contact.reshape(len(contact), -1), axis=1))
                in_contact[a:a + len(contact)] = maps.in_contact.cpu().numpy()
                if colour_model is not None:
                    yield from compose_images(maps.gradients, background, colour_model, settings.noise_std,
                                              settings.seed, a)
            member.close()
            member = _NpyMember(zf, "contact", (t, h, w), np.bool_)
            for bits in contact_bits:
                member.write(np.unpackbits(bits, axis=1, count=h * w).astype(bool).reshape(-1, h, w))
            member.close()

    if colour_model is not None:
        from tactile_slam.io.video import write_video

        write_video(_staged(out / VIDEO), frames(), renderer.config.sensor.fps)
    else:
        for _ in frames():
            pass
    return in_contact


# ---------------------------------------------------------------- reading


@dataclass
class Episode:
    """A simulated episode's ground truth (see the module docstring for the files).

    Attributes:
        path: the folder.
        object_T_sensor: ``(T, 4, 4)`` float64 metres.
        in_contact: ``(T,)`` bool.
        meta: parsed ``meta.yaml``.
    """

    path: Path
    object_T_sensor: np.ndarray
    in_contact: np.ndarray
    meta: dict

    def __len__(self) -> int:
        return len(self.object_T_sensor)

    @property
    def background(self) -> str | None:
        """The background an image-level episode was composed on (``meta.yaml``: a path or
        ``"synthetic"``); None at the gradient level."""
        return (self.meta.get("image") or {}).get("background")

    @property
    def first_contact(self) -> int:
        """Index of the first frame in contact."""
        if not self.in_contact.any():
            raise EpisodeError(f"episode {self.path} has no frame in contact")
        return int(np.argmax(self.in_contact))

    def mesh(self) -> o3d.geometry.TriangleMesh:
        """The object mesh (metres, object frame)."""
        return read_mesh(self.path / MESH)

    def gradients(self) -> tuple[np.ndarray, np.ndarray]:
        """``(gradients (T, H, W, 2) float16, contact (T, H, W) bool)``."""
        path = self.path / GRADIENTS
        if not path.is_file():
            raise EpisodeError(f"missing {path}")
        with np.load(path, allow_pickle=False) as data:
            return data["gradients"], data["contact"]


def read_mesh(path: Path) -> o3d.geometry.TriangleMesh:
    if not path.is_file():
        raise EpisodeError(f"mesh file not found: {path}")
    mesh = o3d.io.read_triangle_mesh(str(path))
    if len(mesh.triangles) == 0:
        raise EpisodeError(f"mesh file has no triangles: {path}")
    mesh.compute_vertex_normals()
    return mesh


def read_episode(path: str | Path) -> Episode:
    """Load an episode folder's poses, contact flags and metadata."""
    path = Path(path)
    if not path.is_dir():
        raise EpisodeError(f"episode folder not found: {path}")
    for name in (POSES, CONTACT, META):
        if not (path / name).is_file():
            raise EpisodeError(f"episode {path} is missing {name}")
    poses = np.load(path / POSES, allow_pickle=False)
    contact = np.load(path / CONTACT, allow_pickle=False)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4):
        raise EpisodeError(f"{path / POSES}: expected (T, 4, 4), got {poses.shape}")
    if contact.shape != (len(poses),):
        raise EpisodeError(f"{path / CONTACT}: expected ({len(poses)},), got {contact.shape}")
    if not np.isfinite(poses).all():
        raise EpisodeError(f"{path / POSES}: non-finite poses")
    meta = yaml.safe_load((path / META).read_text()) or {}
    return Episode(path, poses.astype(np.float64), contact.astype(bool), meta)
