"""Relocalisation against the loop closer's keyframe store, for a front end that lost track.

``Relocaliser.relocalise(image, t_ns)``: ORB + BoW of the image, the best database hits, PnP
RANSAC against each hit's landmarks (stored in the keyframe's cam0 frame), and the pose through
the keyframe's latest odometry pose: ``world_from_body`` in the odometry frame of the matched
keyframe's segment (what the front end tracks in), plus ``map_from_body`` after loop correction.

Thread-safe: the database query runs under the store's lock (the loop closer adds under the
same lock); descriptions are immutable, so verification runs outside it.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from slam.core.calibration import Calibration
from slam.core.geometry import invert_transform
from slam.loop.config import LoopClosureConfig
from slam.loop.store import KeyframeStore, describe_image
from slam.loop.verify import VerifyParams, verify_loop
from slam.loop.vocabulary import Vocabulary, load_default_vocabulary


@dataclass(frozen=True, eq=False)
class Relocalisation:
    """Where an image was found."""

    t_ns: int
    keyframe_id: int  # the matched keyframe
    segment_id: int  # its map segment: world_from_body is in this segment's odometry frame
    world_from_body: np.ndarray  # (4, 4)
    map_from_body: np.ndarray  # (4, 4) after the latest loop correction
    inliers: int
    score: float  # BoW score of the matched keyframe
    elapsed_ms: float


@dataclass(frozen=True)
class _RecentHit:
    """A candidate named by the caller rather than found by the BoW query."""

    kf_id: int
    score: float = 0.0


class Relocaliser:
    """Finds a lost camera among the stored keyframes."""

    def __init__(
        self,
        calib: Calibration,
        store: KeyframeStore,
        cfg: LoopClosureConfig | None = None,
        vocabulary: Vocabulary | None = None,
    ):
        self.cfg = cfg or LoopClosureConfig()
        self.store = store
        self.intr = calib.cameras[0].intrinsics
        self.K = self.intr.K
        self.body_from_cam0 = calib.cameras[0].body_from_cam
        self.cam0_from_body = invert_transform(self.body_from_cam0)
        self.vocab = vocabulary or load_default_vocabulary()
        self.verify_params = VerifyParams(
            min_inliers=self.cfg.reloc_min_inliers,
            min_inlier_ratio=self.cfg.min_inlier_ratio,
            reprojection_px=self.cfg.reprojection_px,
        )
        self.calls = 0
        self.successes = 0
        self.elapsed_ms: list[float] = []

    def stats(self) -> dict[str, object]:
        """Calls, successes and the median time per call (ms) so far."""
        return {
            "calls": self.calls,
            "successes": self.successes,
            "p50_ms": float(np.median(self.elapsed_ms)) if self.elapsed_ms else None,
        }

    def relocalise(
        self,
        image_left: np.ndarray,
        t_ns: int,
        segment_id: int | None = None,
        recent_ids: list[int] | None = None,
    ) -> Relocalisation | None:
        """Pose of ``image_left`` against the stored keyframes (only those of ``segment_id``
        when given), or None. ``recent_ids`` (e.g. the last keyframes before a loss) are
        verified too, whatever their BoW rank: after a short gap they are the likeliest."""
        t0 = time.perf_counter()
        self.calls += 1
        query = describe_image(image_left, self.vocab, self.intr, self.cfg.max_orb_features)
        with self.store.lock:
            if not len(self.store.database):
                self.elapsed_ms.append((time.perf_counter() - t0) * 1e3)
                return None
            skip = None
            if segment_id is not None:
                skip = lambda kf: self.store.description(kf).segment_id != segment_id  # noqa: E731
            hits = self.store.database.query(
                query.bow, exclude=skip, max_results=self.cfg.reloc_candidates
            )
            known = {h.kf_id for h in hits}
            extra = [k for k in (recent_ids or []) if k not in known and self.store.has(k)]
            hits = list(hits) + [_RecentHit(k) for k in extra]  # type: ignore[misc]
            descs = [self.store.description(h.kf_id) for h in hits]
        best = None
        for hit, cand in zip(hits, descs, strict=True):
            res = verify_loop(
                query.xy_undist,
                query.desc,
                cand.landmark_desc,
                cand.landmark_points_cam,
                self.K,
                None,
                self.verify_params,
            )
            if res is not None and (best is None or res.num_inliers > best[1].num_inliers):
                best = (hit, res, cand)
                if res.num_inliers >= 2 * self.cfg.reloc_min_inliers:
                    break  # clearly found: skip the other candidates
        elapsed = (time.perf_counter() - t0) * 1e3
        self.elapsed_ms.append(elapsed)
        if best is None:
            return None
        hit, res, cand = best
        kfbody_from_body = (
            self.body_from_cam0 @ res.candidate_cam_from_query_cam @ self.cam0_from_body
        )
        self.successes += 1
        return Relocalisation(
            t_ns=int(t_ns),
            keyframe_id=cand.kf_id,
            segment_id=cand.segment_id,
            world_from_body=self.store.odometry(cand.kf_id) @ kfbody_from_body,
            map_from_body=self.store.corrected(cand.kf_id) @ kfbody_from_body,
            inliers=res.num_inliers,
            score=hit.score,
            elapsed_ms=elapsed,
        )
