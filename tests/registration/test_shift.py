"""Global shift search (FFT cross-correlation of the contacts' normal maps) and the
registration fallback that starts from it."""

from __future__ import annotations

import importlib
from dataclasses import replace

import pytest
import torch

from tactile_slam.config import NormalFlowConfig
from tactile_slam.registration.normalflow import register
from tactile_slam.registration.result import pose_error
from tactile_slam.registration.shift import correlation_shift

from .surfaces import S, bumpy, frames, rigid, speckled, textured

EYE = torch.eye(4, dtype=torch.float64)
# the module (the package exports a function of the same name)
normalflow_module = importlib.import_module("tactile_slam.registration.normalflow")
MOVES_MM = [(2.5, -1.2), (3.0, 0.0), (0.0, 2.0), (-1.0, -2.2)]


@pytest.fixture(scope="module")
def moved():
    """One reference and four targets moved by ``MOVES_MM`` (x, y), per surface."""
    return {name: frames(surface, [EYE] + [rigid(tx_mm=x, ty_mm=y) for x, y in MOVES_MM])
            for name, surface in (("textured", textured(0)), ("bumpy", bumpy(1)), ("speckled", speckled(0)))}


@pytest.mark.parametrize("factor", [1, 2])
@pytest.mark.parametrize("name", ["textured", "bumpy", "speckled"])
def test_shift_of_translated_touches(moved, name, factor, dtype, device):
    """A reference pixel ``u`` shows up at ``u + t / s`` in a target translated by ``t``: the
    search finds that shift to a pixel at full resolution and to a block (2 px) on 2x2
    block averages, for a batch of targets against one reference."""
    f = moved[name]
    normals, contact = f.normals.to(device=device, dtype=dtype), f.contact.to(device)
    d = correlation_shift(normals[:1], contact[:1], normals[1:], contact[1:], factor=factor)
    assert d.shape == (len(MOVES_MM), 2) and d.dtype == torch.float64 and d.device.type == device.type
    want = torch.tensor(MOVES_MM, dtype=torch.float64) * 1e-3 / S
    assert (d.cpu() - want).abs().max() <= factor, (d, want)
    assert (d.cpu() % factor == 0).all()


def test_shift_pairs_and_no_overlap(moved):
    """Pairs with their own references give each pair's shift; a target without contact
    has no overlap with anything and gets (0, 0); the overlap fraction is checked."""
    f = moved["speckled"]
    ref_n = torch.stack([f.normals[0], f.normals[2]])
    ref_c = torch.stack([f.contact[0], f.contact[2]])
    tar_c = torch.stack([f.contact[1], torch.zeros_like(f.contact[0])])
    d = correlation_shift(ref_n, ref_c, torch.stack([f.normals[1], f.normals[1]]), tar_c)
    want = torch.tensor(MOVES_MM[0], dtype=torch.float64) * 1e-3 / S
    assert (d[0] - want).abs().max() <= 2.0 and d[1].tolist() == [0.0, 0.0]
    with pytest.raises(ValueError, match="min_overlap"):
        correlation_shift(ref_n, ref_c, ref_n, ref_c, min_overlap=0.0)
    for factor in (0, 1.5, True):
        with pytest.raises(ValueError, match="factor"):
            correlation_shift(ref_n, ref_c, ref_n, ref_c, factor=factor)


def test_fallback_starts_from_the_shift_when_the_coarse_retry_fails(moved, monkeypatch):
    """A 3 mm move of a bumpy dome: from the identity the full-resolution solve and the
    coarse fallback both fail; the retry from the searched shift recovers the pose. Where
    the first solve succeeds, no search runs. (With the top-k samples: spread samples let
    the coarse fallback alone recover this move.)"""
    f = moved["bumpy"]
    calls = []
    monkeypatch.setattr(normalflow_module, "correlation_shift",
                        lambda *a, **k: calls.append(len(a[2])) or correlation_shift(*a, **k))
    cfg = NormalFlowConfig(selection="topk", fallback_factors=(16, 4))
    without = register(f[0:1], f[2:3], None, replace(cfg, fallback_shift_search=False))
    assert not bool(without.ok[0]), "test scene: the coarse fallback alone must fail here"
    assert calls == []
    assert bool(register(f[0:1], f[2:3], None, replace(cfg, selection="spread", fallback_shift_search=False)).ok[0])
    res = register(f[0:1], f[2:3], None, cfg)
    rot, trans = pose_error(res.tar_T_ref.double(), rigid(tx_mm=3.0)[None])
    assert bool(res.ok[0]) and float(rot) < 0.05 and float(trans) < 0.005, (float(rot), float(trans))
    assert calls == [1]
    small = frames(bumpy(1), [EYE, rigid(tx_mm=0.2)])
    assert bool(register(small[0:1], small[1:2], None, cfg).ok[0])
    assert calls == [1]


def test_bad_maps_and_non_finite_normals(moved):
    """Wrong shapes and mismatched batches are clear errors; an empty target batch gives no
    shifts; a NaN normal inside the target's contact is left out of the contact instead of
    spoiling every shift."""
    f = moved["speckled"]
    n, c = f.normals, f.contact
    for args in ((n[:1, ..., :2], c[:1], n[1:], c[1:]), (n[:1], c[:1, :10], n[1:], c[1:]),
                 (n[:2], c[:2], n[1:], c[1:]), (n[:1, :100], c[:1, :100], n[1:], c[1:])):
        with pytest.raises(ValueError, match="normals|do not fit"):
            correlation_shift(*args)
    assert correlation_shift(n[:1], c[:1], n[:0], c[:0]).shape == (0, 2)
    tar = n[1:2].clone()
    r, col = (int(v[0]) for v in torch.nonzero(c[1]).T)
    tar[0, r, col] = float("nan")
    d = correlation_shift(n[:1], c[:1], tar, c[1:2])
    want = torch.tensor(MOVES_MM[0], dtype=torch.float64) * 1e-3 / S
    assert (d[0] - want).abs().max() <= 2.0
