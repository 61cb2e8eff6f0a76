"""Curvature SIFT features: keypoints inside the eroded contact, none on flat contact,
exact shift equivariance of the crop logic, the 8-bit mapping, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tactile_slam.geometry.curvature import curvature, normals_from_gradients
from tactile_slam.geometry.morphology import mask_bounds
from tactile_slam.geometry.morphology import erode
from tactile_slam.loop.features import (
    FeatureError, Features, SiftSettings, curvature_features, curvature_image, detect, gaussian_curvature_features,
    image_features,
)
from tests.registration.surfaces import Surface, frames, textured

CLIP = 0.7


@pytest.fixture(scope="module")
def textured_frame():
    return frames(textured(3), [torch.eye(4, dtype=torch.float64)])


def test_smoke_types_and_shapes(textured_frame):
    f = curvature_features(textured_frame.curvature[0], textured_frame.contact[0], CLIP)
    assert isinstance(f, Features)
    assert len(f) >= 8
    assert f.keypoints.shape == (len(f), 2) and f.keypoints.dtype == torch.float32
    assert f.descriptors.shape == (len(f), 128) and f.descriptors.dtype == torch.float32


def test_keypoints_inside_eroded_contact(textured_frame):
    contact = textured_frame.contact[0]
    f = curvature_features(textured_frame.curvature[0], contact, CLIP)
    inner = erode(contact[None], 5, border_is_contact=False)[0]
    rows, cols = f.keypoints[:, 1].round().long(), f.keypoints[:, 0].round().long()
    assert bool(inner[rows, cols].all())
    # and they are spread over the contact, not only at one spot
    assert float(f.keypoints[:, 0].std()) > 10.0 and float(f.keypoints[:, 1].std()) > 10.0


def test_flat_contact_has_no_keypoints():
    fr = frames(Surface(flat=True, depth=0.5e-3), [torch.eye(4, dtype=torch.float64)])
    assert int(fr.contact.sum()) > 10000  # a large contact, but featureless inside
    f = curvature_features(fr.curvature[0], fr.contact[0], CLIP)
    assert len(f) == 0


def test_no_contact_is_empty(textured_frame):
    none = torch.zeros_like(textured_frame.contact[0])
    f = curvature_features(textured_frame.curvature[0], none, CLIP)
    assert len(f) == 0 and f.descriptors.shape == (0, 128)


def test_integer_shift_equivariance(textured_frame):
    """Shifting the map and the contact by whole pixels shifts every keypoint by the
    same amount and leaves its descriptor unchanged (crop and shift-back are exact)."""
    curv, contact = textured_frame.curvature[0], textured_frame.contact[0]
    dy, dx = 7, -11
    f0 = curvature_features(curv, contact, CLIP)
    f1 = curvature_features(torch.roll(curv, (dy, dx), (0, 1)), torch.roll(contact, (dy, dx), (0, 1)), CLIP)
    assert len(f0) == len(f1)
    o0 = torch.argsort(f0.keypoints[:, 0] * 1000 + f0.keypoints[:, 1])
    o1 = torch.argsort(f1.keypoints[:, 0] * 1000 + f1.keypoints[:, 1])
    torch.testing.assert_close(f1.keypoints[o1], f0.keypoints[o0] + torch.tensor([dx, dy], dtype=torch.float32))
    torch.testing.assert_close(f1.descriptors[o1], f0.descriptors[o0])


def test_curvature_image_mapping():
    L = torch.tensor([[-0.7, -0.35, 0.0], [0.2, 0.7, 0.69999], [-0.9, 0.9, 0.011]])
    expected = np.trunc((np.clip(L.numpy().astype(np.float64), -0.7, 0.7) + 0.7) / 1.4 * 255).astype(np.uint8)
    out = curvature_image(L, CLIP)
    assert out.dtype == torch.uint8
    np.testing.assert_array_equal(out.numpy(), expected)
    assert int(curvature_image(torch.zeros(2, 3, 3), CLIP)[0, 0, 0]) == 127


def test_mask_bounds():
    m = torch.zeros(10, 12, dtype=torch.bool)
    assert mask_bounds(m) is None
    m[2:5, 3:9] = True
    assert mask_bounds(m) == (2, 5, 3, 9)


def test_image_features_within_contact(textured_frame):
    contact = textured_frame.contact[0]
    grey = curvature_image(textured_frame.curvature[0], CLIP)
    bgr = grey[..., None].expand(-1, -1, 3).contiguous()
    f = image_features(bgr, contact)
    assert len(f) > 0
    inner = erode(contact[None], 5, border_is_contact=False)[0]
    assert bool(inner[f.keypoints[:, 1].round().long(), f.keypoints[:, 0].round().long()].all())


def test_float64_curvature_gives_the_same_features(textured_frame, dtype):
    f32 = curvature_features(textured_frame.curvature[0], textured_frame.contact[0], CLIP)
    f = curvature_features(textured_frame.curvature[0].to(dtype), textured_frame.contact[0], CLIP)
    torch.testing.assert_close(f.keypoints, f32.keypoints)
    torch.testing.assert_close(f.descriptors, f32.descriptors)


def test_kornia_backend_inside_contact(textured_frame):
    pytest.importorskip("kornia")
    contact = textured_frame.contact[0]
    f = curvature_features(textured_frame.curvature[0], contact, CLIP, SiftSettings(backend="kornia", max_features=128))
    assert len(f) > 0 and f.descriptors.shape == (len(f), 128)
    inner = erode(contact[None], 5, border_is_contact=False)[0]
    assert bool(inner[f.keypoints[:, 1].round().long(), f.keypoints[:, 0].round().long()].all())


def test_exceptions(textured_frame):
    curv, contact = textured_frame.curvature[0], textured_frame.contact[0]
    with pytest.raises(FeatureError, match="NaN"):
        curvature_features(torch.full_like(curv, float("nan")), contact, CLIP)
    with pytest.raises(FeatureError, match="single"):
        curvature_features(curv[None], contact, CLIP)
    with pytest.raises(FeatureError, match="contact"):
        curvature_features(curv, contact[:10], CLIP)
    with pytest.raises(FeatureError, match="backend"):
        curvature_features(curv, contact, CLIP, SiftSettings(backend="surf"))
    with pytest.raises(FeatureError, match="clip"):
        curvature_image(curv, 0.0)
    with pytest.raises(FeatureError, match="uint8"):
        image_features(torch.zeros(240, 320, 3), contact)


def test_edge_threshold_admits_keypoints_on_lines():
    """Two crossing ridges: OpenCV's edge test keeps only the crossing at the default 10;
    a higher ``edge_threshold`` also keeps extrema along the ridges (line-like texture,
    such as a shell's ribs and growth lines)."""
    r, c = np.mgrid[:240, :320].astype(np.float64)
    d1 = np.abs(r - 120 - 0.3 * (c - 160)) / np.hypot(1.0, 0.3)  # distance to ridge 1 (px)
    d2 = np.abs(c - 100 + 0.2 * r) / np.hypot(1.0, 0.2)
    img = 127 + 60 * np.exp(-d1**2 / 8.0) + 60 * np.exp(-d2**2 / 4.5)
    image = torch.from_numpy(img.clip(0, 255).astype(np.uint8))
    contact = torch.zeros(240, 320, dtype=torch.bool)
    contact[20:220, 20:300] = True
    default = detect(image, contact, SiftSettings())
    lines = detect(image, contact, SiftSettings(edge_threshold=80.0))
    assert len(lines) > 1.5 * len(default) > 0
    x, y = lines.keypoints[:, 0].double().numpy(), lines.keypoints[:, 1].double().numpy()
    on_ridge = np.minimum(np.abs(y - 120 - 0.3 * (x - 160)) / np.hypot(1.0, 0.3),
                          np.abs(x - 100 + 0.2 * y) / np.hypot(1.0, 0.2))
    assert (on_ridge < 8.0).all()  # DoG extrema sit on a ridge or its flanks


class TestGaussianCurvatureFeatures:
    """SIFT on the Gaussian-curvature map (``loop.feature_map: gaussian``)."""

    def test_smoke_and_inside_contact(self, textured_frame):
        contact = textured_frame.contact[0]
        f = gaussian_curvature_features(textured_frame.normals[0], contact, 5, 1.1, CLIP)
        assert len(f) >= 8 and f.descriptors.shape == (len(f), 128)
        inner = erode(contact[None], 5, border_is_contact=False)[0]
        assert bool(inner[f.keypoints[:, 1].round().long(), f.keypoints[:, 0].round().long()].all())

    def test_ridges_give_the_laplacian_keypoints_and_this_map_none(self):
        """Straight parallel ridges in a disc of contact (a ribbed face): SIFT on the
        Laplacian finds keypoints along them, which no other touch can place (a shift
        along a ridge looks the same); on the Gaussian curvature the ridges vanish."""
        r, c = torch.meshgrid(torch.arange(240.0), torch.arange(320.0), indexing="ij")
        h = 2.0 * torch.sin(2 * math.pi * (c * math.cos(0.4) + r * math.sin(0.4)) / 13.0)  # px
        gy, gx = torch.gradient(h, dim=(0, 1))
        g = torch.stack([gx, gy], -1)[None]
        contact = ((r - 120) ** 2 + (c - 160) ** 2 < 90**2)[None]
        lap = curvature_features(curvature(g, contact)[0], contact[0], CLIP)
        gauss = gaussian_curvature_features(normals_from_gradients(g)[0], contact[0], 5, 1.1, CLIP)
        assert len(lap) >= 8 and len(gauss) == 0

    def test_exceptions(self, textured_frame):
        n, contact = textured_frame.normals[0], textured_frame.contact[0]
        with pytest.raises(FeatureError, match="NaN"):
            gaussian_curvature_features(torch.full_like(n, float("nan")), contact, 5, 1.1, CLIP)
        with pytest.raises(FeatureError, match="single"):
            gaussian_curvature_features(n[None], contact, 5, 1.1, CLIP)
