import pytest

from tactile_slam.config import Config, ConfigError, digit, gelsight_mini, load_config, lower_limit
from tactile_slam.pipeline.offline import OfflinePipeline

GELSLAM_YAML = """
device_config:
  device_name: "GelSight Mini"
  ppmm: 0.0634
  imgh: 240
  imgw: 320
  raw_imgh: 2464
  raw_imgw: 3280
  framerate: 25
  calibration_model_path: "model/nnmodel.pth"
contact_mask_config:
  color_dist_threshold: 15
  height_threshold: 0.2
gelslam_config:
  track_config:
    contact_threshold: 500
    scr_threshold: 0.3
    ccs_threshold: 0.7
  pose_graph_config:
    coverage_graph_overlap_threshold: 50
    min_sift_inliers: 8
    scr_threshold: 0.3
    ccs_threshold: 0.7
"""


def test_presets():
    mini = gelsight_mini()
    assert mini.sensor.mm_per_px == 0.0634 and mini.sensor.shape == (240, 320) and mini.sensor.fps == 25
    assert (mini.sensor.raw_width, mini.sensor.raw_height) == (3280, 2464)
    assert mini.final_erode_px == 5
    assert mini.min_contact_px == pytest.approx(500)
    assert mini.height_threshold_px == pytest.approx(3.1546, abs=1e-3)
    d = digit()
    assert d.sensor.mm_per_px == 0.0405 and d.sensor.fps == 60
    assert (d.sensor.raw_width, d.sensor.raw_height) == (640, 480)
    # pixel-valued constants follow the sensor scale
    assert d.min_contact_px == pytest.approx(500 * (0.0634 / 0.0405) ** 2)


def test_gelslam_layout(tmp_path):
    p = tmp_path / "config.yaml"
    p.write_text(GELSLAM_YAML)
    cfg = Config.from_yaml(p)
    assert cfg.sensor.mm_per_px == 0.0634  # ppmm means mm per pixel: never inverted
    assert cfg.sensor.model_path == str((tmp_path / "model/nnmodel.pth").resolve())
    assert cfg.tracking.ccs_threshold == 0.7 and cfg.loop.min_sift_inliers == 8
    assert cfg.min_contact_px == pytest.approx(500)
    assert cfg.loop.coverage_overlap_mm2 == pytest.approx(50 * 0.0634**2)


def test_own_layout_roundtrip(tmp_path):
    cfg = Config()
    cfg.normalflow.n_samples = 1234
    cfg.normalflow.coarse_factors = (4, 2)
    cfg.sensor.name = "X"
    p = tmp_path / "c.yaml"
    cfg.save(p)
    back = load_config(p)
    assert back.normalflow.n_samples == 1234 and back.sensor.name == "X"
    assert back.normalflow.coarse_factors == (4, 2)
    assert back.to_dict() == cfg.to_dict()


@pytest.mark.parametrize(
    "text,match",
    [
        ("sensor: {mm_per_px: -1}", "mm_per_px"),
        ("sensr: {}", "unknown config section"),
        ("sensor: {foo: 1}", "unknown key sensor.foo"),
        ("device_config: {ppmx: 1}", "unknown key device_config.ppmx"),
        ("- a\n- b", "mapping"),
        ("sensor: [1, 2", "not valid YAML"),
        ("curvature: {blur_ksize: 4}", "odd"),
        # values of the wrong type name their key instead of failing later in the algorithm
        ("tracking: {max_deg_per_s: fast}", r"tracking.max_deg_per_s must be of type float or null, got 'fast'"),
        ("normalflow: {n_samples: lots}", r"normalflow.n_samples must be of type int or null"),
        ("normalflow: {n_samples: 3000.5}", r"normalflow.n_samples must be of type int"),
        ("normalflow: {max_iters: true}", r"normalflow.max_iters must be of type int"),
        ("loop: {consistency: 'yes'}", r"loop.consistency must be of type bool"),
        ("recon: {all_groups: maybe}", r"recon.all_groups must be of type bool, got 'maybe'"),
        ("normalflow: {coarse_factors: 4}", r"normalflow.coarse_factors must be a list"),
        ("normalflow: {coarse_factors: [4, x]}", r"normalflow.coarse_factors\[1\] must be of type int"),
        ("sensor: {name: 3}", r"sensor.name must be of type str"),
        # NormalFlow's ranges are checked at load, before any frame is read
        ("normalflow: {stall_check_iters: -3}", r"normalflow.stall_check_iters must be >= 0, got -3"),
        ("normalflow: {max_iters: 0}", r"normalflow.max_iters, min_iters and coarse_max_iters must be >= 1"),
        ("normalflow: {jacobian: numeric}", r"normalflow.jacobian must be one of"),
        ("normalflow: {selection: best}", r"normalflow.selection must be one of \('spread', 'topk'"),
        ("normalflow: {sample_cell_px: 0}", r"normalflow.sample_cell_px must be >= 1, got 0"),
        ("normalflow: {fallback_factors: [1]}", r"normalflow.fallback_factors must be >= 2"),
        # YAML's .nan and .inf pass a float annotation; a NaN threshold made every test false
        ("normalflow: {ccs_threshold: .nan}", r"normalflow.ccs_threshold must be a finite number, got nan"),
        ("tracking: {max_deg_per_s: .inf}", r"tracking.max_deg_per_s must be a finite number, got inf"),
        ("posegraph: {sigma_trans_m: -.inf}", r"posegraph.sigma_trans_m must be a finite number"),
        # ranges of settings used late (meshing after the run) or never checked before
        ("tracking: {ccs_threshold: 2}", r"tracking.ccs_threshold must be in \[0, 1\], got 2.0"),
        ("loop: {scr_threshold: -0.1}", r"loop.scr_threshold must be in \[0, 1\]"),
        ("contact: {erode: -1}", r"contact.erode must be >= 0, got -1"),
        ("curvature: {blur_sigma: 0}", r"curvature.blur_sigma must be > 0, got 0.0"),
        ("posegraph: {max_iters: 0}", r"posegraph.max_iters must be >= 1, got 0"),
        ("posegraph: {lambda_factor: 1}", r"posegraph.lambda_factor must be > 1"),
        ("recon: {voxel_mm: 0}", r"recon.voxel_mm must be > 0"),
        ("recon: {trim_density_quantile: 1}", r"recon.trim_density_quantile must be in \[0, 1\)"),
        ("recon: {poisson_min_depth: 9, poisson_max_depth: 8}",
         r"recon.poisson_max_depth must be >= poisson_min_depth"),
        ("loop: {ransac_confidence: 1}", r"loop.ransac_confidence must be in \(0, 1\)"),
        ("recon: {poisson_threads: 0}", r"recon.poisson_threads must be -1 \(every core\) or an integer >= 1"),
        ("contact: {given_masks: loose}", r"contact.given_masks must be one of \('final', 'region'\), got 'loose'"),
        # settings that crashed mid-run in OpenCV, or silently emptied the run, before the first frame
        ("loop: {sift_octave_layers: 0}", r"loop.sift_octave_layers must be >= 1, got 0"),
        ("loop: {ransac_refine_iters: -1}", r"loop.ransac_refine_iters must be >= 0, got -1"),
        ("loop: {max_init_rot_deg: -1}", r"loop.max_init_rot_deg must be >= 0"),
        ("loop: {coverage_depth_gate_mm: -1}", r"loop.coverage_depth_gate_mm must be > 0"),
        ("loop: {ambiguity_ratio: -1}", r"loop.ambiguity_ratio must be > 0"),
        ("loop: {gate_margin_mm: -1}", r"loop.gate_margin_mm must be >= 0"),
        ("loop: {min_sift_inliers: 2}", None),  # the detector's own check, when the pipeline is built
        ("posegraph: {sigma_rot_rad: 0}", r"posegraph.sigma_rot_rad must be > 0, got 0"),
        ("normalflow: {min_iters: 60}", r"normalflow.min_iters \(60\) must be <= max_iters \(50\)"),
        ("normalflow: {n_samples: 5}", r"normalflow.n_samples \(5\) must be >= normalflow.min_shared \(10\)"),
        ("tracking: {fallback_factors: [1]}", r"tracking.fallback_factors must be integers >= 2, got \[1\]"),
        # string settings are checked at load, naming the key
        ("posegraph: {robust: bogus}", r"posegraph.robust must be one of \('none', 'huber', 'cauchy', 'gnc'\)"),
        ("loop: {sift_backend: vlfeat}", r"loop.sift_backend must be one of \('opencv', 'kornia'\)"),
        ("loop: {mode: half}", r"loop.mode must be one of"),
        ("loop: {feature_map: raw}", r"loop.feature_map must be one of"),
        ("loop: {merge_distinct: any}", r"loop.merge_distinct must be one of"),
        ("tracking: {init: guess}", r"tracking.init must be one of"),
        ("tracking: {keyframe_edge: both}", r"tracking.keyframe_edge must be one of"),
        ("sensor: {width: 2, height: 8}", r"sensor size 2x8 is too small for the curvature blur \(curvature.blur_ksize "
                                          r"5: at least 3 px each way\)"),
        ("sensor: {ppmm: 0.05, mm_per_px: 0.05}", r"sensor.ppmm and sensor.mm_per_px are the same setting"),
        ("normalflow: {trans_tol_m: '1e-5'}", r"normalflow.trans_tol_m must be of type float, got '1e-5'"),  # quoted
        # the GelSLAM layout: misspelt sub-sections and values of the wrong type name their key
        ("gelslam_config: {track_confg: {ccs_threshold: 0.5}}", r"unknown key gelslam_config.track_confg"),
        ("gelslam_config: [1]", r"gelslam_config must be a mapping, got \[1\]"),
        ("device_config: [1]", r"device_config must be a mapping"),
        ("gelslam_config: {track_config: 3}", r"gelslam_config.track_config must be a mapping"),
        ("device_config: {ppmm: [1]}", r"device_config.ppmm must be of type float, got \[1\]"),
        ("device_config: {ppmm: abc}", r"device_config.ppmm must be of type float, got 'abc'"),
        ("gelslam_config: {track_config: {contact_threshold: '500'}}",
         r"gelslam_config.track_config.contact_threshold must be of type float, got '500'"),
        ("gelslam_config: {pose_graph_config: {coverage_graph_overlap_threshold: .nan}}",
         r"coverage_graph_overlap_threshold must be a finite number"),
    ],
)
def test_bad_configs(tmp_path, text, match):
    p = tmp_path / "c.yaml"
    p.write_text(text)
    if match is None:
        Config.from_yaml(p)
        return
    with pytest.raises(ConfigError, match=match):
        Config.from_yaml(p)


def test_the_loop_detector_names_each_bad_setting():
    from tactile_slam.loop.detector import LoopDetector, LoopError

    for name, value in (("min_sift_inliers", 2), ("max_candidates", 0), ("verify_batch", 0)):
        cfg = Config()
        setattr(cfg.loop, name, value)
        with pytest.raises(LoopError, match=f"loop.{name} must be >= "):
            LoopDetector(cfg)


def test_exponents_without_a_dot_are_floats(tmp_path):
    """PyYAML reads ``1e-5`` as a string (YAML 1.1); the defaults are written that way,
    so the loader reads it as YAML 1.2 does."""
    p = tmp_path / "c.yaml"
    p.write_text("normalflow: {trans_tol_m: 1e-5, rot_tol: 2E-4, degenerate_eig: +1e-7}\n"
                 "posegraph: {lambda_max: 1e5, sigma_trans_m: 1.5e-4}\nsensor: {name: 1e3x}\n")
    cfg = Config.from_yaml(p)
    assert (cfg.normalflow.trans_tol_m, cfg.normalflow.rot_tol, cfg.normalflow.degenerate_eig) == (1e-5, 2e-4, 1e-7)
    assert (cfg.posegraph.lambda_max, cfg.posegraph.sigma_trans_m) == (1e5, 1.5e-4)
    assert cfg.sensor.name == "1e3x"
    cfg.save(p)
    assert Config.from_yaml(p).to_dict() == cfg.to_dict()


def test_a_saved_config_loads_back_with_names_that_look_like_exponents(tmp_path):
    cfg = Config()
    cfg.sensor.name = "3E8"
    cfg.save(tmp_path / "c.yaml")
    assert Config.from_yaml(tmp_path / "c.yaml").sensor.name == "3E8"


@pytest.mark.parametrize("text,key", [("tracking: {fallback_factors: [3]}", "tracking.fallback_factors"),
                                      ("normalflow: {coarse_factors: [7]}", "normalflow.coarse_factors")])
def test_factors_must_divide_the_sensor_size_to_track(tmp_path, text, key):
    """A size the factors do not divide loads (calibration never tracks); a pipeline refuses
    it before reading a frame, naming the key and how to turn the levels off."""
    p = tmp_path / "c.yaml"
    p.write_text(text)
    cfg = Config.from_yaml(p)
    with pytest.raises(ConfigError, match=rf"{key} must divide the sensor size 320x240, got \d \(an empty list"):
        OfflinePipeline(iter(()), cfg, tmp_path / "out")
    odd = Config.from_dict({"sensor": {"width": 322, "height": 242}})  # the default fallback factor 4 does not divide
    with pytest.raises(ConfigError, match="tracking.fallback_factors must divide the sensor size 322x242"):
        odd.check_factors()
    Config.from_dict({"sensor": {"width": 322, "height": 242}, "tracking": {"fallback_factors": []}}).check_factors()


def test_ppmm_is_an_alias_of_mm_per_px(tmp_path):
    """method.md 1.1: GelSLAM's ``ppmm`` (millimetres per pixel) also in our layout."""
    p = tmp_path / "c.yaml"
    p.write_text("sensor: {ppmm: 0.05}\n")
    assert Config.from_yaml(p).sensor.mm_per_px == 0.05


def test_normalflow_config_checks_its_ranges_without_the_loader():
    """Registration checks a NormalFlowConfig built in Python: a NaN threshold made every
    pair fail, even at CCS 1."""
    from tactile_slam.config import NormalFlowConfig

    with pytest.raises(ConfigError, match="normalflow.ccs_threshold must be in"):
        NormalFlowConfig(ccs_threshold=float("nan")).check()
    NormalFlowConfig().check()


def test_values_are_typed(tmp_path):
    """ints are accepted where floats are expected (YAML writes 30 for 30.0), null where
    the field allows it; lists become tuples."""
    p = tmp_path / "c.yaml"
    p.write_text("tracking: {max_deg_per_s: null, max_mm_per_s: 30}\n"
                 "normalflow: {coarse_factors: [8, 4], n_samples: null, fallback_factors: [16, 4]}\n"
                 "contact: {height_fraction: null}\n")
    cfg = Config.from_yaml(p)
    assert cfg.tracking.max_deg_per_s is None
    assert cfg.tracking.max_mm_per_s == 30.0 and isinstance(cfg.tracking.max_mm_per_s, float)
    assert cfg.normalflow.coarse_factors == (8, 4) and cfg.normalflow.n_samples is None
    assert cfg.normalflow.fallback_factors == (16, 4)
    assert cfg.contact.height_fraction is None and cfg.depth_test[1] is None  # the public fixed rule


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")


def test_every_preset_and_the_defaults_pass_the_ranges():
    for name in (None, "gelsight_mini", "digit"):
        load_config(name).validate()


def test_a_pipeline_validates_a_config_built_in_python(tmp_path):
    """A Config changed in Python skips the YAML loader's checks; the pipeline runs them
    when it is built, before any frame is read."""
    cfg = Config()
    cfg.recon.voxel_mm = -1.0
    with pytest.raises(ConfigError, match="recon.voxel_mm must be > 0"):
        OfflinePipeline(iter(()), cfg, tmp_path / "out")


def test_lower_limit_holds_the_decoded_limit_only_for_decoded_frames():
    assert lower_limit(10.0, 5.5, decoded=False) == 10.0
    assert lower_limit(10.0, 5.5, decoded=True) == 5.5
    assert lower_limit(0.5, 0.8, decoded=True) == 0.5  # the lower holds
    assert lower_limit(None, 5.5, decoded=True) == 5.5 and lower_limit(None, 5.5, decoded=False) is None
    assert lower_limit(None, None, decoded=True) is None
