import cv2
import numpy as np
import pytest
import torch
import yaml

from tactile_slam.calibration.colour_model import ColourModel
from tactile_slam.cli.main import main
from tactile_slam.io.video import VideoSource
from tactile_slam.config import GELSIGHT_MINI_ENV, REPO_ROOT, gelsight_mini_data
from tactile_slam.sim.episode import (EpisodeError, ImplausibleMotionWarning, SimulationSettings,
                                      SyntheticBackgroundWarning,
                                      background_source, compose_images, load_background_image, read_episode,
                                      simulate_episode, synthetic_background)
from tactile_slam.sim.objects import MeshSizeWarning
from tactile_slam.sim.renderer import GelRenderer


@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    out = tmp_path_factory.mktemp("ep")
    simulate_episode(out, SimulationSettings(object="seed", kind="tracking", frames=24, seed=3))
    return out


def test_layout_and_contents(episode):
    names = {p.name for p in episode.iterdir()}
    assert names == {"gt_poses.npy", "in_contact.npy", "gt_gradients.npz", "object.ply", "meta.yaml"}
    ep = read_episode(episode)
    assert len(ep) == 24 and ep.object_T_sensor.shape == (24, 4, 4)
    assert not ep.in_contact[:10].any() and ep.in_contact[10:].all() and ep.first_contact == 10
    g, c = ep.gradients()
    assert g.shape == (24, 240, 320, 2) and g.dtype == np.float16
    assert c.shape == (24, 240, 320) and c.dtype == bool
    assert np.array_equal(c.reshape(24, -1).sum(1) >= 500, ep.in_contact)
    meta = yaml.safe_load((episode / "meta.yaml").read_text())
    assert meta["kind"] == "tracking" and meta["seed"] == 3 and meta["level"] == "gradients"
    assert ep.background is None  # composed on no background at the gradient level
    assert meta["sensor"]["mm_per_px"] == pytest.approx(0.0634)
    # ground truth matches a fresh render of the stored poses with the stored mesh
    maps = GelRenderer(ep.mesh()).render(ep.object_T_sensor[[12, 20]])
    assert np.allclose(g[[12, 20]].astype(np.float32), maps.gradients.numpy(), atol=2e-3)
    assert np.array_equal(c[[12, 20]], maps.contact.numpy())


def test_motion_steps_in_meta_and_a_warning_beyond_the_tracker_limits(episode, tmp_path):
    """meta.yaml records the largest frame step among in-contact frames, computed here
    independently; an episode whose steps exceed the tracker's limits warns."""
    import warnings

    from tactile_slam.config import Config

    ep = read_episode(episode)
    steps = yaml.safe_load((episode / "meta.yaml").read_text())["motion_steps"]
    T = ep.object_T_sensor
    both = ep.in_contact[:-1] & ep.in_contact[1:]
    rel = np.linalg.inv(T[:-1]) @ T[1:]
    ang = np.degrees(np.arccos(np.clip((np.trace(rel[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
    assert steps["max_deg_per_frame"] == pytest.approx(ang[both].max(), rel=1e-6)
    assert steps["max_mm_per_frame"] == pytest.approx(np.linalg.norm(rel[both, :3, 3], axis=1).max() * 1e3, rel=1e-6)
    assert steps["limit_deg_per_frame"] == pytest.approx(Config().tracking.max_deg_per_s / 25.0)
    assert steps["steps_over_limit"] == 0 and steps["first_step_over_limit"] is None  # a smooth seed path
    strict = Config()
    strict.tracking.max_deg_per_s = 1e-3
    with pytest.warns(ImplausibleMotionWarning, match="simulated frame steps move faster"):
        simulate_episode(tmp_path, SimulationSettings(object="seed", kind="tracking", frames=24, seed=3), strict)
    steps = yaml.safe_load((tmp_path / "meta.yaml").read_text())["motion_steps"]
    assert steps["steps_over_limit"] == int((ang[both] > 1e-3 / 25.0).sum()) > 0
    assert steps["first_step_over_limit"] >= 10  # the lead-in is out of contact
    with warnings.catch_warnings():
        warnings.simplefilter("error", ImplausibleMotionWarning)  # the default limits: no warning
        simulate_episode(tmp_path / "again", SimulationSettings(object="seed", kind="tracking", frames=24, seed=3))


def test_deterministic(episode, tmp_path):
    simulate_episode(tmp_path, SimulationSettings(object="seed", kind="tracking", frames=24, seed=3))
    assert np.array_equal(np.load(tmp_path / "gt_poses.npy"), np.load(episode / "gt_poses.npy"))
    with np.load(tmp_path / "gt_gradients.npz") as a, np.load(episode / "gt_gradients.npz") as b:
        assert np.array_equal(a["gradients"], b["gradients"]) and np.array_equal(a["contact"], b["contact"])


def test_image_level_video_is_exact(tmp_path):
    torch.manual_seed(0)
    model_path = ColourModel(hidden=(8,)).save(tmp_path / "colour.pt")
    bg = synthetic_background((240, 320))
    cv2.imwrite(str(tmp_path / "bg.png"), bg)
    out = tmp_path / "ep"
    rc = main(["simulate", "--object", "seed", "--kind", "tracking", "--frames", "14", "--seed", "1",
               "--level", "image", "--colour-model", str(model_path), "--background", str(tmp_path / "bg.png"),
               "--out", str(out)])
    assert rc == 0
    video = np.stack([f.bgr for f in VideoSource(out / "gelsight.avi")])
    assert video.shape == (14, 240, 320, 3)
    assert np.array_equal(cv2.imread(str(out / "background.png")), bg)
    ep = read_episode(out)
    assert ep.background == str(tmp_path / "bg.png")
    maps = GelRenderer(ep.mesh()).render(ep.object_T_sensor)
    expected = compose_images(maps.gradients, bg, ColourModel.load(model_path), 1.0, 1, 0)
    assert np.array_equal(video, expected)  # lossless and reproducible
    # contact-free lead-in: image = background + model(0) + noise only
    lead = video[:10].astype(float) - bg - ColourModel.load(model_path)(torch.zeros(1, 240, 320, 2)).numpy()
    assert np.abs(lead).mean() < 1.5


def test_background_from_the_gelsight_mini_folder(tmp_path, monkeypatch):
    bg = np.full((240, 320, 3), 7, np.uint8)
    (tmp_path / "calibration").mkdir()
    cv2.imwrite(str(tmp_path / "calibration" / "background.png"), bg)
    monkeypatch.setenv(GELSIGHT_MINI_ENV, str(tmp_path))
    assert gelsight_mini_data() == tmp_path
    img, source = load_background_image(None, (240, 320))
    assert np.array_equal(img, bg) and source == str(tmp_path / "calibration" / "background.png")
    assert background_source() == source and background_source("mine.png") == "mine.png"
    monkeypatch.delenv(GELSIGHT_MINI_ENV)
    assert gelsight_mini_data() == REPO_ROOT.parent / "shared" / "data" / "gelsight_mini"


def test_background_falls_back_to_synthetic_with_a_warning(tmp_path, monkeypatch):
    # a checkout away from ../shared (a git worktree elsewhere) composed its images on the
    # synthetic background without a word, and image-level results changed with the folder
    monkeypatch.setenv(GELSIGHT_MINI_ENV, str(tmp_path / "absent"))
    with pytest.warns(SyntheticBackgroundWarning, match=GELSIGHT_MINI_ENV):
        img, source = load_background_image(None, (240, 320))
    assert source == "synthetic" and np.array_equal(img, synthetic_background((240, 320)))
    assert background_source() == "synthetic"


def test_compose_images_noise_independent_of_batching():
    g = torch.zeros(4, 240, 320, 2)
    model = lambda x: torch.zeros(*x.shape[:3], 3)  # noqa: E731
    bg = synthetic_background((240, 320))
    whole = compose_images(g, bg, model, 2.0, 7, 0)
    parts = np.concatenate([compose_images(g[:2], bg, model, 2.0, 7, 0), compose_images(g[2:], bg, model, 2.0, 7, 2)])
    assert np.array_equal(whole, parts)
    assert 1.5 < (whole.astype(float) - bg).std() < 2.5


def test_errors(tmp_path):
    with pytest.raises(EpisodeError, match="colour model"):
        simulate_episode(tmp_path, SimulationSettings(level="image", colour_model=str(tmp_path / "none.pt"), frames=12))
    with pytest.raises(EpisodeError, match="level"):
        simulate_episode(tmp_path, SimulationSettings(level="pixels"))
    with pytest.raises(EpisodeError, match="not found"):
        read_episode(tmp_path / "missing")
    (tmp_path / "e").mkdir()
    with pytest.raises(EpisodeError, match="gt_poses"):
        read_episode(tmp_path / "e")
    assert main(["simulate", "--object", "teapot", "--out", str(tmp_path / "x")]) == 2


@pytest.mark.parametrize("field, value, message", [
    ("noise_std", -1.0, "image noise"), ("noise_std", float("nan"), "image noise"),
    ("mesh_scale", 0.0, "mesh scale"), ("mesh_scale", float("inf"), "mesh scale"), ("batch", 0, "batch"),
])
def test_bad_settings_are_refused_before_rendering(tmp_path, field, value, message):
    """A negative or NaN noise std was skipped silently (only ``> 0`` adds noise), so an
    episode meant to be noisy came out clean; bad values now stop before anything is written."""
    with pytest.raises(EpisodeError, match=message):
        simulate_episode(tmp_path / "ep", SimulationSettings(frames=12, **{field: value}))
    assert not (tmp_path / "ep").exists()


@pytest.mark.slow
def test_image_level_decodes_back_to_ground_truth(tmp_path, mini_data):
    """Synthetic images through the real calibration MLP give the rendered gradients back
    (the colour model is the calibration step's; skipped until it exists)."""
    from tactile_slam.calibration.model import GradientDecoder, load_model
    from tactile_slam.config import Config
    from tactile_slam.geometry.curvature import normals_from_gradients
    from tactile_slam.geometry.frame import FrameBuilder
    from tactile_slam.sim.episode import DEFAULT_COLOUR_MODEL

    if not DEFAULT_COLOUR_MODEL.is_file():
        pytest.skip(f"no colour model at {DEFAULT_COLOUR_MODEL}")
    simulate_episode(tmp_path, SimulationSettings(object="lime", kind="tracking", frames=24, level="image"))
    video = np.stack([f.bgr for f in VideoSource(tmp_path / "gelsight.avi")])
    cfg = Config()
    model, _ = load_model(mini_data / "reference_model" / "nnmodel.pth")
    background = torch.from_numpy(video[:10].astype(np.float32).mean(0))
    frame = FrameBuilder(cfg, GradientDecoder(model, background, cfg.contact.mlp_skip_color_dist)).from_bgr(
        torch.from_numpy(video[10:]))
    g, c = read_episode(tmp_path).gradients()
    gt = torch.from_numpy(g[10:].astype(np.float32))
    cos = (normals_from_gradients(frame.gradients) * normals_from_gradients(gt)).sum(-1).clamp(-1, 1)
    err = torch.rad2deg(torch.acos(cos))[torch.from_numpy(c[10:])]
    assert err.median() < 8.0  # measured 4.4 deg with a colour model fitted on the example presses
    assert frame.in_contact.all()


def test_background_unreadable_or_wrong_size_is_refused(tmp_path):
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(EpisodeError, match="cannot read background image"):
        load_background_image(tmp_path / "bad.png", (240, 320))
    cv2.imwrite(str(tmp_path / "small.png"), np.zeros((120, 160, 3), np.uint8))
    with pytest.raises(EpisodeError, match="160x120, expected 320x240"):
        load_background_image(tmp_path / "small.png", (240, 320))


def _sphere_file(path, radius):
    import open3d as o3d

    o3d.io.write_triangle_mesh(str(path), o3d.geometry.TriangleMesh.create_sphere(radius, resolution=30))
    return path


def test_an_episode_without_contact_is_refused_and_writes_nothing(tmp_path):
    """A 1 mm user mesh gave an episode with no frame in contact, whose meta.yaml said
    first_contact_frame 0: now it is refused, and the folder is left as it was."""
    tiny = _sphere_file(tmp_path / "tiny.ply", 0.0005)
    with pytest.warns(MeshSizeWarning), pytest.raises(EpisodeError, match=r"no frame of the 14-frame tracking "
                                                                        r"episode is in contact.*1 mm across"):
        simulate_episode(tmp_path / "new", SimulationSettings(object=str(tiny), frames=14))
    assert not (tmp_path / "new").exists()
    old = tmp_path / "old"
    old.mkdir()
    (old / "notes.txt").write_text("kept")
    with pytest.warns(MeshSizeWarning), pytest.raises(EpisodeError, match="no frame"):
        simulate_episode(old, SimulationSettings(object=str(tiny), frames=14))
    assert [p.name for p in old.iterdir()] == ["notes.txt"]  # no gradients, no .part files
    with pytest.warns(MeshSizeWarning):
        assert main(["simulate", "--object", str(tiny), "--frames", "14", "--out", str(tmp_path / "cli")]) == 2


def test_meta_records_the_size_and_scale_applied(episode, tmp_path):
    """A catalogue object records its size and no scale, a mesh file its scale and no
    size; a flag for the other kind of object is refused before anything is written."""
    obj = yaml.safe_load((episode / "meta.yaml").read_text())["object"]
    assert (obj["size_mm"], obj["mesh_scale"]) == (9.0, None) and obj["extent_mm"] == pytest.approx(9.0, abs=0.3)
    in_mm = _sphere_file(tmp_path / "sphere_mm.ply", 6.0)
    simulate_episode(tmp_path / "ep", SimulationSettings(object=str(in_mm), frames=14, mesh_scale=1e-3))
    meta = yaml.safe_load((tmp_path / "ep" / "meta.yaml").read_text())
    assert (meta["object"]["size_mm"], meta["object"]["mesh_scale"]) == (None, 1e-3)
    assert meta["object"]["extent_mm"] == pytest.approx(12.0, rel=1e-3)
    ep = read_episode(tmp_path / "ep")
    assert ep.in_contact[meta["first_contact_frame"]] and meta["contact_frames"] == ep.in_contact.sum() > 0
    for flags in (["--object", str(in_mm), "--size-mm", "30"], ["--object", "seed", "--mesh-scale", "1e-3"]):
        assert main(["simulate", *flags, "--frames", "14", "--out", str(tmp_path / "flag")]) == 2
        assert not (tmp_path / "flag").exists()
