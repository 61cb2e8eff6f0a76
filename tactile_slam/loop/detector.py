"""Loop detection: candidates, SIFT + 2-D RANSAC, batched NormalFlow verification
(method.md sections 6.2-6.4, ablations 9.5).

For a query keyframe ``t`` the detector

1. takes the eligible keyframes (the active coverage keyframes, given by the caller)
   minus ``t`` itself and ``t - 1`` of the same session (already an odometry edge);
2. drops same-group keyframes whose contact footprint cannot overlap the query's under
   the current pose estimates (:func:`tactile_slam.loop.retrieval.pose_gate`);
3. when more than ``max_candidates`` remain, keeps the ones with the most descriptor
   votes in the :class:`~tactile_slam.loop.retrieval.DescriptorIndex`;
4. matches each against the query and fits the 2-D similarity by RANSAC; pairs with at
   least ``min_sift_inliers`` inliers are the loop candidates, each with an SE(3)
   initial guess about the image centre;
5. verifies all candidates as one NormalFlow batch with the loop CCS/SCR thresholds,
   optionally also requiring the refined pose to stay near the 2-D guess; each accepted
   pair is a :class:`Loop`. The *query* is the batch's one shared reference and the
   candidates are its targets (method.md 6.4 has candidate = reference): one
   preparation per query instead of one per candidate, and the shared-reference solve;
   measured faster and with more correct loops (docs/loops.md).

Modes (``LoopConfig.mode``): ``full``; ``only_sift`` (the lifted 2-D estimate is the
measurement, no NormalFlow, no CCS/SCR); ``only_nf`` (no SIFT: NormalFlow from identity
on every candidate, CCS/SCR decide); ``image_sift`` (SIFT on the keyframes' raw grey
images instead of curvature; keyframes must carry ``image``).
"""

from __future__ import annotations

import math
import time
from collections.abc import Collection, Mapping, Sequence
from dataclasses import dataclass, fields, replace

import torch

from tactile_slam.config import FEATURE_MAPS, LOOP_DETECTOR_MODES, Config
from tactile_slam.geometry.frame import CroppedFrame, Frame, window_batch
from tactile_slam.loop.features import (Features, SiftSettings, curvature_features, gaussian_curvature_features,
                                        image_features)
from tactile_slam.loop.matching import RansacSettings, match, self_similarity, similarity_to_se3
from tactile_slam.loop.retrieval import DescriptorIndex, Footprint, IndexSettings, footprints, pose_gate
from tactile_slam.posegraph import se3
from tactile_slam.registration.normalflow import (
    PreparedReference,
    prepare_reference,
    reference_settings,
    register_prepared,
    window_multiple,
)
from tactile_slam.registration.result import RegistrationResult
from tactile_slam.tracking.keyframe import Keyframe



class LoopError(ValueError):
    """Invalid input to loop detection (bad mode, unknown or duplicate keyframe, bad frame)."""


@dataclass
class Loop:
    """An accepted loop: a between factor from keyframe ``ref_id`` to ``tar_id``.

    Attributes:
        ref_id: the earlier (candidate) keyframe.
        tar_id: the query keyframe.
        ref_T_tar: ``(4, 4)`` float64 metres, pose of the query keyframe in the candidate
            keyframe (maps query-sensor coordinates into candidate-sensor coordinates):
            the measurement of the between factor.
        ccs: curvature cosine similarity of the verification (NaN in ``only_sift``).
        scr: shared curvature ratio of the verification (NaN in ``only_sift``).
        inliers: 2-D RANSAC inliers (0 in ``only_nf``).
        init_tar_T_ref: ``(4, 4)`` float64 initial guess NormalFlow started from
            (the lifted 2-D similarity; identity in ``only_nf``).
        repetitive: either keyframe's texture matches another part of itself
            (:func:`~tactile_slam.loop.matching.self_similarity`): the match may be a whole
            period or a symmetry away, so the loop is no independent evidence.
        probe: found by verifying a pair predicted by another loop between the same two
            groups (:mod:`tactile_slam.loop.probe`), not by SIFT retrieval (``inliers`` 0).
        ambiguous: the pair also verifies from another start at another pose
            (:mod:`tactile_slam.loop.ambiguity`): like ``repetitive``, no evidence of where
            the touches were; set by the back end on loops between two groups.
        depth_known: both keyframes show undeformed gel (:attr:`Keyframe.depth_known`); if
            not, the z translation of ``ref_T_tar`` carries that keyframe's guessed height
            zero (set by the back end). The keyframe's odometry carries the same offset, so
            the graph stays consistent: only that keyframe's own z is off.
        tilt_sigma_deg: the standard deviation the pose graph gives the loop's rotation
            about the sensor's x and y axes (``loop.decoded_tilt_sigma_deg``, set by the back
            end on loops between keyframes decoded from images); ``None``: the graph's
            default, like every other component.
        conditioning: the verification's smallest-to-largest eigenvalue ratio of the
            normal equations (:attr:`RegistrationResult.conditioning`): how evenly the
            touch constrains the five registered directions (NaN in ``only_sift``).
    """

    ref_id: int
    tar_id: int
    ref_T_tar: torch.Tensor
    ccs: float
    scr: float
    inliers: int
    init_tar_T_ref: torch.Tensor
    repetitive: bool = False
    probe: bool = False
    ambiguous: bool = False
    depth_known: bool = True
    tilt_sigma_deg: float | None = None
    conditioning: float = math.nan

    @property
    def says_where(self) -> bool:
        """Whether the loop is evidence of where the two touches were: neither
        ``repetitive`` nor ``ambiguous``."""
        return not (self.repetitive or self.ambiguous)

    def to_dict(self) -> dict:
        """JSON-ready: poses as nested lists (metres)."""
        return {"ref_id": self.ref_id, "tar_id": self.tar_id, "ref_T_tar": self.ref_T_tar.tolist(),
                "ccs": self.ccs, "scr": self.scr, "inliers": self.inliers,
                "init_tar_T_ref": self.init_tar_T_ref.tolist(), "repetitive": self.repetitive,
                "probe": self.probe, "ambiguous": self.ambiguous, "depth_known": self.depth_known,
                "tilt_sigma_deg": self.tilt_sigma_deg, "conditioning": self.conditioning}


@dataclass
class DetectionStats:
    """Counters and cumulative times (seconds) over all :meth:`LoopDetector.detect` calls.

    ``candidates`` are the pairs that passed RANSAC (the paper's "loop candidates"; in
    ``only_nf`` every verified pair); ``pairs`` the pairs left after the exclusions,
    ``gated`` those the pose gate removed, ``matched`` those matched and RANSAC-fitted.
    """

    queries: int = 0
    pairs: int = 0
    gated: int = 0
    matched: int = 0
    candidates: int = 0
    verified: int = 0
    rejected_deviation: int = 0
    loops: int = 0
    time_features: float = 0.0
    time_retrieval: float = 0.0
    time_matching: float = 0.0
    time_verification: float = 0.0

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}


def pose_deviation(a_T: torch.Tensor, b_T: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rotation angle (degrees) and in-plane translation distance (mm) between
    ``(B, 4, 4)`` transforms ``a_T`` and ``b_T`` (z translation ignored: the 2-D guess has
    none). Returns two ``(B,)`` float64 tensors."""
    r = a_T[:, :3, :3].transpose(1, 2) @ b_T[:, :3, :3]
    cos = ((r.diagonal(dim1=1, dim2=2).sum(-1) - 1.0) / 2.0).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos)), torch.linalg.vector_norm(a_T[:, :2, 3] - b_T[:, :2, 3], dim=1) * 1e3


class LoopDetector:
    """Finds loops between a query keyframe and earlier keyframes.

    Args:
        config: settings; ``config.loop`` for detection, ``config.normalflow`` for the
            verification (with the loop CCS/SCR thresholds substituted).
        mode: overrides ``config.loop.mode`` (one of :data:`~tactile_slam.config.LOOP_DETECTOR_MODES`).
    """

    def __init__(self, config: Config, mode: str | None = None):
        lc = config.loop
        self.config = config
        self.mode = mode or lc.mode
        if self.mode not in LOOP_DETECTOR_MODES:
            raise LoopError(f"loop mode must be one of {LOOP_DETECTOR_MODES}, got {self.mode!r}")
        for name, least in (("min_sift_inliers", 3), ("max_candidates", 1), ("verify_batch", 1)):
            if getattr(lc, name) < least:
                raise LoopError(f"loop.{name} must be >= {least}, got {getattr(lc, name)}")
        if not lc.sift_edge_threshold > 0:
            raise LoopError(f"loop.sift_edge_threshold must be > 0, got {lc.sift_edge_threshold}")
        if lc.feature_map not in FEATURE_MAPS:
            raise LoopError(f"loop.feature_map must be one of {FEATURE_MAPS}, got {lc.feature_map!r}")
        self.sift = SiftSettings(lc.sift_backend, lc.sift_contrast_threshold, lc.sift_octave_layers,
                                 lc.sift_max_features, config.final_erode_px, lc.sift_edge_threshold)
        self.ransac = RansacSettings(lc.min_sift_inliers, lc.ransac_iterations, lc.ransac_threshold_px,
                                     lc.ransac_confidence, lc.ransac_refine_iters, lc.ambiguity_ratio)
        self.nf_config = replace(config.normalflow, ccs_threshold=lc.ccs_threshold, scr_threshold=lc.scr_threshold)
        self.index = DescriptorIndex(IndexSettings(lc.retrieval_neighbours, lc.retrieval_min_votes,
                                                   lc.retrieval_exact_max))
        self._features: dict[int, Features] = {}
        self._matchable: set[int] = set()  # ids with at least min_sift_inliers keypoints
        self._footprints: dict[int, Footprint | None] = {}  # by id, removed keyframes included
        self._repetitive: set[int] = set()  # ids whose texture matches another part of itself
        self._query: tuple[Keyframe, Features] | None = None  # the last query's features, reused by add
        self._removed: set[int] = set()
        self.stats = DetectionStats()

    # ------------------------------------------------------------------ map
    def __len__(self) -> int:
        return len(self._features)

    def __contains__(self, kf_id: int) -> bool:
        return kf_id in self._features

    def features(self, kf_id: int) -> Features:
        """The features of an added, not removed keyframe."""
        if kf_id not in self._features:
            raise LoopError(f"keyframe {kf_id} is not in the loop detector")
        return self._features[kf_id]

    def extract(self, keyframe: Keyframe) -> Features:
        """Features of a keyframe for this mode: SIFT on its curvature map
        (``loop.feature_map``: the Laplacian or the Gaussian curvature), or on its image."""
        frame = _check_keyframe(keyframe)
        t0 = time.perf_counter()
        if self.mode == "image_sift":
            if keyframe.image is None:
                raise LoopError(f"mode 'image_sift' needs keyframe images; keyframe {keyframe.id} has none")
            feats = image_features(keyframe.image, frame.contact[0].cpu(), self.sift)
        elif self.config.loop.feature_map == "gaussian":
            cc = self.config.curvature
            feats = gaussian_curvature_features(frame.normals[0].cpu(), frame.contact[0].cpu(), cc.blur_ksize,
                                                cc.blur_sigma, cc.clip, self.sift)
        else:
            feats = curvature_features(frame.curvature[0].cpu(), frame.contact[0].cpu(),
                                       self.config.curvature.clip, self.sift)
        self.stats.time_features += time.perf_counter() - t0
        return feats

    def add(self, keyframe: Keyframe) -> Features:
        """Extract and index a keyframe's features (call once per keyframe).

        Returns:
            its :class:`Features` (empty when the keyframe has no keypoints).
        """
        if keyframe.id in self._features or keyframe.id in self._removed:
            raise LoopError(f"keyframe {keyframe.id} was already added")
        feats = self._query_features(keyframe)
        self._query = None
        self._features[keyframe.id] = feats
        if len(feats) >= self.ransac.min_inliers:
            self._matchable.add(keyframe.id)
        if self_similarity(feats, self.ransac) is not None:
            self._repetitive.add(keyframe.id)
        self.index.add(keyframe.id, feats.descriptors)
        self.footprint(keyframe)
        return feats

    def remove(self, kf_id: int) -> None:
        """Forget a keyframe (deactivated by the coverage set): it is never a candidate again."""
        if kf_id not in self._features:
            raise LoopError(f"keyframe {kf_id} is not in the loop detector")
        del self._features[kf_id]
        self._matchable.discard(kf_id)
        self.index.remove(kf_id)
        self._removed.add(kf_id)

    def footprint(self, keyframe: Keyframe) -> Footprint | None:
        """The keyframe's contact footprint (None without contact); computed once per
        keyframe id and kept, for removed keyframes too."""
        if keyframe.id not in self._footprints:
            frame = keyframe.frame
            self._footprints[keyframe.id] = footprints(frame.height, frame.contact, frame.mm_per_px / 1000.0)[0]
        return self._footprints[keyframe.id]

    def is_repetitive(self, keyframe: Keyframe) -> bool:
        """Whether the keyframe's texture matches another part of itself
        (:func:`~tactile_slam.loop.matching.self_similarity`); stored for added keyframes
        (removed ones included)."""
        if keyframe.id in self._features or keyframe.id in self._removed:
            return keyframe.id in self._repetitive
        return self_similarity(self._query_features(keyframe), self.ransac) is not None

    def _query_features(self, keyframe: Keyframe) -> Features:
        """Features of a keyframe not added yet; kept for the :meth:`add` that usually
        follows its detection, so they are extracted once."""
        if self._query is None or self._query[0] is not keyframe:
            self._query = (keyframe, self.extract(keyframe))
        return self._query[1]

    # ------------------------------------------------------------------ detection
    def detect(self, query: Keyframe, eligible: Collection[int], group_of: Mapping[int, int],
               start_T_kf: Mapping[int, torch.Tensor], keyframes: Mapping[int, Keyframe]) -> list[Loop]:
        """Loops between ``query`` and earlier keyframes.

        Args:
            query: the new keyframe (added or not; its features are reused if added).
            eligible: ids that may be candidates (the active coverage keyframes); ids
                removed from the detector are skipped.
            group_of: keyframe id -> connected-group id (the pose gate applies within
                the query's group; keyframes missing here are not gated).
            start_T_kf: keyframe id -> ``(4, 4)`` float64 pose in its group's start
                frame (metres); used only by the pose gate.
            keyframes: keyframe id -> :class:`Keyframe` (frames of the candidates).

        Returns:
            accepted :class:`Loop` s, by candidate id; empty when there is nothing to match.
        """
        _check_keyframe(query)
        self.stats.queries += 1
        cands = self._exclusions(query, eligible, keyframes)
        cands = self._gate(query, cands, group_of, start_T_kf)
        if not cands:
            return []
        if self.mode == "only_nf":
            self.stats.candidates += len(cands)
            init = torch.eye(4, dtype=torch.float64).expand(len(cands), 4, 4)
            return self._verify_and_accept(query, cands, init, [0] * len(cands), keyframes)
        q_feats = self._features.get(query.id)
        if q_feats is None:
            q_feats = self._query_features(query)
        if len(q_feats) < self.ransac.min_inliers:
            return []
        t0 = time.perf_counter()
        cands = [r for r in cands if r in self._matchable]
        if len(cands) > self.config.loop.max_candidates:
            cands = sorted(self.index.query(q_feats.descriptors, cands, self.config.loop.max_candidates))
        t1 = time.perf_counter()
        self.stats.time_retrieval += t1 - t0
        found, inits, inliers = [], [], []
        shape, s = query.maps.shape, query.maps.mm_per_px / 1000.0
        for r in cands:
            sim = match(self._features[r], q_feats, self.ransac)
            if sim is not None:
                found.append(r)
                inits.append(similarity_to_se3(sim.M, shape, s))
                inliers.append(sim.inliers)
        self.stats.matched += len(cands)
        self.stats.candidates += len(found)
        self.stats.time_matching += time.perf_counter() - t1
        if not found:
            return []
        init = torch.stack(inits)
        if self.mode == "only_sift":
            ref_T_tar = se3.inverse(init)
            rep = self.is_repetitive(query)
            loops = [Loop(r, query.id, ref_T_tar[i], math.nan, math.nan, inliers[i], init[i],
                          rep or r in self._repetitive) for i, r in enumerate(found)]
            self.stats.loops += len(loops)
            return loops
        return self._verify_and_accept(query, found, init, inliers, keyframes)

    def _exclusions(self, query: Keyframe, eligible: Collection[int], keyframes: Mapping[int, Keyframe]) -> list[int]:
        ids = set(eligible) - self._removed
        ids.discard(query.id)
        never = ids - self._features.keys()
        if never:
            raise LoopError(f"eligible keyframe {min(never)} was never added to the loop detector")
        missing = ids - keyframes.keys()
        if missing:
            raise LoopError(f"eligible keyframe {min(missing)} is missing from the keyframe map")
        prev = query.id - 1
        if prev in ids and keyframes[prev].session == query.session:
            ids.discard(prev)  # odometry edge
        out = sorted(ids)
        self.stats.pairs += len(out)
        return out

    def _gate(self, query: Keyframe, cands: list[int], group_of: Mapping[int, int],
              start_T_kf: Mapping[int, torch.Tensor]) -> list[int]:
        margin = self.config.loop.gate_margin_mm
        if margin is None or query.id not in group_of or query.id not in start_T_kf:
            return cands
        q_fp = self.footprint(query)
        if q_fp is None:
            return cands
        g = group_of[query.id]
        same = [r for r in cands if group_of.get(r) == g and r in start_T_kf and self._footprints[r] is not None]
        if not same:
            return cands
        poses = torch.stack([torch.as_tensor(start_T_kf[r], dtype=torch.float64).cpu() for r in same])
        keep = pose_gate(q_fp, start_T_kf[query.id], [self._footprints[r] for r in same], poses, margin * 1e-3)
        dropped = {r for r, k in zip(same, keep.tolist()) if not k}
        self.stats.gated += len(dropped)
        return [r for r in cands if r not in dropped]

    def verify(self, query: Keyframe, refs: Sequence[Keyframe], init_tar_T_ref: torch.Tensor,
               exhaustive: bool = False) -> RegistrationResult:
        """NormalFlow between the query and each candidate keyframe, in batches of
        ``loop.verify_batch`` pairs, with the loop CCS/SCR thresholds.

        ``exhaustive``: every pair runs to convergence or ``max_iters`` (no stall check,
        ``NormalFlowConfig.stall_check_iters``). For the question "does any other start
        verify?" (:mod:`~tactile_slam.loop.ambiguity`, probes), where a slow alternative
        that a stall check would stop must still count.

        The query is the one prepared reference of every batch (its samples, its CCS and
        SCR) and the candidates are the targets, read from windows around their stored
        contact boxes (:func:`~tactile_slam.geometry.frame.window_batch`), not full
        maps; the poses are returned the other way round, as the candidates' ``tar_T_ref``.

        Args:
            query: the query keyframe.
            refs: ``B`` candidate keyframes.
            init_tar_T_ref: ``(B, 4, 4)`` float64 initial ``query_T_candidate`` (metres).

        Returns:
            a :class:`RegistrationResult` of ``B`` pairs whose ``tar_T_ref`` is
            ``query_T_candidate`` (``ok`` = passed every check).
        """
        if len(refs) == 0 or init_tar_T_ref.shape != (len(refs), 4, 4):
            raise LoopError(f"need B >= 1 references and (B, 4, 4) initial poses, got {len(refs)} and "
                            f"{tuple(init_tar_T_ref.shape)}")
        t0 = time.perf_counter()
        prep = self._reference(query)
        step = self.config.loop.verify_batch
        config = replace(self.nf_config, stall_check_iters=0) if exhaustive else self.nf_config
        multiple = window_multiple(config)
        out = []
        for a in range(0, len(refs), step):
            tar = window_batch([_stored_maps(kf) for kf in refs[a:a + step]], multiple).to(prep.device)
            res = register_prepared(prep, tar, se3.inverse(init_tar_T_ref[a:a + step].double()).to(prep.device),
                                    config)
            out.append(replace(res, tar_T_ref=se3.inverse(res.tar_T_ref.double())))
        self.stats.verified += len(refs)
        self.stats.time_verification += time.perf_counter() - t0
        return RegistrationResult.cat(out)

    def _reference(self, query: Keyframe) -> PreparedReference:
        """The query prepared as the reference of its verification: the tracker's
        preparation when the keyframe still carries one made with the same settings
        (identical result, one preparation fewer), else a new one."""
        frame = _check_keyframe(query)
        prep = query.prepared
        if (isinstance(prep, PreparedReference) and prep.settings == reference_settings(self.nf_config)
                and prep.dtype == frame.normals.dtype and prep.device == frame.device and len(prep) == 1
                and prep.shape == frame.shape):
            return prep
        return prepare_reference(frame, self.nf_config)

    def _verify_and_accept(self, query: Keyframe, cands: list[int], init: torch.Tensor, inliers: list[int],
                           keyframes: Mapping[int, Keyframe]) -> list[Loop]:
        res = self.verify(query, [keyframes[r] for r in cands], init)
        T = res.tar_T_ref.cpu()
        ok = res.ok.cpu().clone()
        lc = self.config.loop
        if self.mode != "only_nf" and (lc.max_init_rot_deg is not None or lc.max_init_trans_mm is not None):
            rot, trans = pose_deviation(T, init)
            far = torch.zeros_like(ok)
            if lc.max_init_rot_deg is not None:
                far |= rot > lc.max_init_rot_deg
            if lc.max_init_trans_mm is not None:
                far |= trans > lc.max_init_trans_mm
            self.stats.rejected_deviation += int((ok & far).sum())
            ok &= ~far
        ref_T_tar = se3.inverse(T)
        rep = self.is_repetitive(query) if bool(ok.any()) else False
        cond = res.conditioning.cpu()
        loops = [Loop(r, query.id, ref_T_tar[i], float(res.ccs[i]), float(res.scr[i]), inliers[i], init[i].clone(),
                      rep or r in self._repetitive, conditioning=float(cond[i]))
                 for i, r in enumerate(cands) if bool(ok[i])]
        self.stats.loops += len(loops)
        return loops


def _stored_maps(keyframe: Keyframe) -> Frame | CroppedFrame:
    """The keyframe's maps as stored (cropped or full), checked to be one frame."""
    if len(keyframe.maps) != 1:
        raise LoopError(f"keyframe {keyframe.id} must hold a single frame (B = 1), got B = {len(keyframe.maps)}")
    return keyframe.maps


def _check_keyframe(keyframe: Keyframe) -> Frame:
    _stored_maps(keyframe)
    return keyframe.frame
