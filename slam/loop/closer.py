"""The loop closer: place recognition -> verification -> gates -> pose graph -> correction.

VINS-Fusion-style drift correction: the front and back ends keep running in their *odometry*
world; the loop closer keeps a pose graph over all keyframes and publishes, after each
optimisation, a ``map_from_odom`` transform per map segment and the corrected pose of every
keyframe. The VIO window is never rebuilt.

Graph: one node per keyframe; odometry edges between consecutive keyframes of one segment (from
their best known odometry poses, refreshed with :meth:`LoopCloser.update_odometry`); loop edges
(robust, GNC by default) between verified revisits. Segments stay separate components until a
loop links them; each optimisation covers the component of the new loop, with its oldest
keyframe fixed.

Guards against perceptual aliasing (identical textures in different places), in order:
BoW temporal consistency (``LoopDetector``), PnP inliers and inlier ratio, a *plausibility gate*
(the loop may move the query keyframe by no more than the drift the odometry could have
accumulated since the candidate: ``gate_base + gate_ratio * path length``), a second agreeing
loop for links between segments (no odometry there to gate with), and the robust kernel.

``LoopCloser`` is a plain class (no threads): ``add_keyframe`` returns a :class:`LoopEvent`;
with ``inline_pgo`` it optimises at once and the event carries the correction; otherwise the
caller runs :func:`run_pgo` on ``closer.pgo_request()`` (e.g. in a worker process) and hands the
outcome back with :meth:`LoopCloser.apply_pgo`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import cv2
import numpy as np

from slam.core.calibration import Calibration
from slam.core.geometry import (
    invert_transform,
    rotation_angle_rad,
    skew,
    so3_exp_batch,
    so3_log,
)
from slam.core.messages import Keyframe, KeyframeInertial, LoopCorrection
from slam.loop.config import LoopClosureConfig
from slam.loop.database import LoopDetector, LoopDetectorParams
from slam.loop.global_ba import (
    GlobalBaParams,
    GlobalBaResult,
    KeyframeObservations,
    global_bundle_adjustment,
)
from slam.loop.store import KeyframeDescription, KeyframeStore, describe_keyframe
from slam.loop.verify import (
    LoopVerification,
    VerifyParams,
    refine_on_patches,
    verify_loop,
    verify_loop_landmarks,
)
from slam.loop.vocabulary import Vocabulary, load_default_vocabulary
from slam.posegraph import (
    DEFAULT_KERNEL_WIDTH,
    GNC_INLIER_CHI2,
    PgoOptions,
    PoseEdge,
    PoseGraph,
    information_from_sigmas,
    optimize,
)

COVISIBILITY_EDGES = ("off", "found", "tracked")  # loop.covisibility_edges


def odometry_sigmas(rel: np.ndarray, dt_s: float, cfg: LoopClosureConfig) -> tuple[float, float]:
    """(translation sigma m, rotation sigma rad) per axis of an odometry edge spanning
    ``rel`` (prev_from_next) and ``dt_s`` seconds.

    Drift modelled as a random walk in time (variances add along the chain, so a gap bridged
    by IMU dead reckoning gets the large sigma it deserves) plus terms proportional to the
    distance travelled and the angle turned (scale and gyro scale errors)."""
    length = float(np.linalg.norm(rel[:3, 3]))
    angle = rotation_angle_rad(rel[:3, :3])
    dt = max(float(dt_s), 0.0)
    sigma_m = float(
        np.sqrt(
            cfg.odom_sigma_m**2
            + (cfg.odom_sigma_ratio * length) ** 2
            + cfg.odom_sigma_m_per_sqrt_s**2 * dt
        )
    )
    sigma_rad = float(
        np.sqrt(
            cfg.odom_sigma_rad**2
            + (cfg.odom_sigma_rad_ratio * angle) ** 2
            + cfg.odom_sigma_rad_per_sqrt_s**2 * dt
        )
    )
    return sigma_m, sigma_rad


def robust_threshold(cfg: LoopClosureConfig) -> float:
    """``PgoOptions.robust_threshold`` for ``cfg.robust``, widened by ``robust_sigma_scale``."""
    scale = cfg.robust_sigma_scale
    if cfg.robust == "gnc":
        return GNC_INLIER_CHI2 * scale**2
    return DEFAULT_KERNEL_WIDTH.get(cfg.robust, 0.0) * scale


def loop_information(
    method: str, cfg: LoopClosureConfig, fitted: np.ndarray | None = None
) -> np.ndarray:
    """Information (6x6, g2o order) of a loop edge verified by ``method``; ``fitted``: the
    patch refinement's (body frame, see ``LoopCloser._refine_on_patches``), used as it is."""
    if fitted is not None:
        return fitted
    scale = 1.0 if method == "landmarks" else cfg.orb_loop_sigma_factor
    return information_from_sigmas(cfg.loop_sigma_m * scale, cfg.loop_sigma_rad * scale)


@dataclass(frozen=True, eq=False)
class PgoRequest:
    """A picklable pose-graph problem (for a worker process)."""

    request_id: int
    world_from_node: dict[int, np.ndarray]
    odometry_edges: tuple[PoseEdge, ...]
    loop_edges: tuple[PoseEdge, ...]
    loop_ids: tuple[int, ...]
    fixed_id: int
    robust: str
    robust_threshold: float = 0.0  # PgoOptions.robust_threshold (0 = the default)


@dataclass(frozen=True, eq=False)
class PgoOutcome:
    """The optimised poses, which loops survived, and the cost."""

    request_id: int
    world_from_node: dict[int, np.ndarray]
    loop_ids: tuple[int, ...]
    loop_inliers: np.ndarray  # (len(loop_ids),) bool
    seconds: float
    initial_chi2: float
    final_chi2: float
    iterations: int


def run_pgo(req: PgoRequest) -> PgoOutcome:
    """Optimise a :class:`PgoRequest` (module-level: runs in a spawned worker process)."""
    graph = PoseGraph.from_poses(req.world_from_node, req.odometry_edges, req.loop_edges)
    res = optimize(
        graph,
        PgoOptions(
            robust=req.robust,  # type: ignore[arg-type]
            robust_threshold=req.robust_threshold,
            chordal_init=False,
            fixed_id=req.fixed_id,
        ),
    )
    return PgoOutcome(
        request_id=req.request_id,
        world_from_node=res.graph.world_from_node(),
        loop_ids=req.loop_ids,
        loop_inliers=np.asarray(res.loop_inliers, dtype=bool),
        seconds=res.seconds,
        initial_chi2=res.initial_chi2,
        final_chi2=res.final_chi2,
        iterations=res.iterations,
    )


@dataclass
class LoopRecord:
    """One loop edge in the graph."""

    loop_id: int
    query_kf_id: int
    match_kf_id: int
    match_body_from_query_body: np.ndarray
    inliers: int
    t_ns: int
    active: bool = True  # False once PGO's robust kernel rejected it
    method: str = "landmarks"  # how it was verified: "landmarks" or "orb" (see _verify)
    landmark_pairs: np.ndarray | None = None  # (M, 2) query / match landmark ids it matched
    information: np.ndarray | None = None  # 6x6 g2o order, body frame: the patch fit's


@dataclass(frozen=True, eq=False)
class LoopEvent:
    """What happened to one keyframe's loop query (None from add_keyframe when nothing).

    ``status``: ``rejected`` (verification or a gate failed; see ``reason``), ``pending``
    (verified, waiting for a confirming loop), ``accepted`` (edge added to the graph).
    """

    t_ns: int
    query_kf_id: int
    match_kf_id: int
    status: str
    reason: str
    inliers: int
    loop_ids: tuple[int, ...] = ()
    correction: LoopCorrection | None = None


@dataclass
class LoopStats:
    keyframes: int = 0
    detections: int = 0
    verified: int = 0
    accepted: int = 0
    rejected_verification: int = 0
    rejected_gate: int = 0
    rejected_unconfirmed: int = 0
    rejected_by_pgo: int = 0
    patch_refined: int = 0
    covisibility_attempts: int = 0
    covisibility_edges: int = 0
    pgo_runs: int = 0
    pgo_ms: list[float] = field(default_factory=list)
    describe_ms: list[float] = field(default_factory=list)
    query_ms: list[float] = field(default_factory=list)
    verify_ms: list[float] = field(default_factory=list)
    covisibility_ms: list[float] = field(default_factory=list)
    keyframe_cpu_ms: list[float] = field(default_factory=list)
    """CPU time (the calling thread's) of each ``add_keyframe``: unlike the wall times above,
    it does not grow when the worker waits for a core on a busy machine."""
    cpu_s: dict[str, float] = field(default_factory=dict)
    """CPU time (s, the calling thread's) per step: describe, query, verify, refine (patch),
    pgo (request, optimisation, result), fusion and adjustment (the end of the run)."""

    def add_cpu(self, step: str, since_s: float) -> float:
        """Count the thread's CPU time since ``since_s`` (``time.thread_time()``) to ``step``;
        returns the time now."""
        now = time.thread_time()
        self.cpu_s[step] = self.cpu_s.get(step, 0.0) + now - since_s
        return now

    def summary(self) -> dict[str, object]:
        from slam.core.latency import latency_summary as pct

        return {
            "keyframes": self.keyframes,
            "detections": self.detections,
            "verified": self.verified,
            "accepted": self.accepted,
            "rejected_verification": self.rejected_verification,
            "rejected_gate": self.rejected_gate,
            "rejected_unconfirmed": self.rejected_unconfirmed,
            "rejected_by_pgo": self.rejected_by_pgo,
            "patch_refined": self.patch_refined,
            "covisibility_attempts": self.covisibility_attempts,
            "covisibility_edges": self.covisibility_edges,
            "covisibility": pct(self.covisibility_ms),
            "pgo_runs": self.pgo_runs,
            "pgo": pct(self.pgo_ms),
            "describe": pct(self.describe_ms),
            "query": pct(self.query_ms),
            "verify": pct(self.verify_ms),
            "keyframe_cpu": pct(self.keyframe_cpu_ms),
            "cpu_s": {k: round(v, 3) for k, v in sorted(self.cpu_s.items())},
        }


@dataclass
class _Pending:
    """A verified loop between segments waiting for a second, agreeing one."""

    record: LoopRecord
    query_seg: int
    match_seg: int
    map_from_query_map: np.ndarray  # the alignment the loop implies
    kf_count: int


class LoopCloser:
    """Loop detection, verification and pose-graph correction over all keyframes."""

    def __init__(
        self,
        calib: Calibration,
        cfg: LoopClosureConfig | None = None,
        vocabulary: Vocabulary | None = None,
        inline_pgo: bool = True,
        store: KeyframeStore | None = None,
    ):
        self.cfg = cfg or LoopClosureConfig()
        if self.cfg.covisibility_edges not in COVISIBILITY_EDGES:
            raise ValueError(
                f"loop.covisibility_edges must be one of {COVISIBILITY_EDGES}, "
                f"got {self.cfg.covisibility_edges!r}"
            )
        self.calib = calib
        self.intr = calib.cameras[0].intrinsics
        self.K = self.intr.K
        self.body_from_cam0 = calib.cameras[0].body_from_cam
        self.cam0_from_body = invert_transform(self.body_from_cam0)
        self.vocab = vocabulary or load_default_vocabulary()
        self.inline_pgo = inline_pgo
        self.store = store or KeyframeStore()
        c = self.cfg
        self.detector = LoopDetector(
            params=LoopDetectorParams(
                min_normalised_score=c.min_normalised_score,
                exclude_recent=c.exclude_recent_keyframes,
                exclude_recent_ns=int(c.exclude_recent_s * 1e9),
                min_eligible=c.min_eligible_keyframes,
                min_consecutive=c.min_consecutive,
            ),
            database=self.store.database,
        )
        self.verify_params = VerifyParams(
            min_inliers=c.min_inliers,
            min_inlier_ratio=c.min_inlier_ratio,
            reprojection_px=c.reprojection_px,
            guided_radius_px=c.guided_radius_px,
            guided_min_inliers=c.guided_min_inliers,
        )
        self.orb = cv2.ORB_create()
        self.stats = LoopStats()
        # graph state
        self.kf_ids: list[int] = []
        self.segment_of: dict[int, int] = {}
        self.t_ns_of: dict[int, int] = {}
        self.odom: dict[int, np.ndarray] = {}
        self.optimised: dict[int, np.ndarray] = {}  # map_from_body from the latest PGO
        self.map_from_odom: dict[int, np.ndarray] = {}  # per segment
        self.path_m: dict[int, float] = {}  # odometry path length from the segment start
        self.last_of_segment: dict[int, int] = {}
        self.prev_in_segment: dict[int, int] = {}
        self.component: dict[int, int] = {}  # segment -> root segment (union-find)
        self.track_start_of_landmark: dict[int, int] = {}  # keyframe id
        self.last_kf_of_landmark: dict[int, int] = {}
        self.first_kf_of_landmark: dict[int, int] = {}
        self.loops: list[LoopRecord] = []
        self.covisibility_edges: list[PoseEdge] = []  # map reuse's ties, see _add_covisibility_edge
        self.map_generation = 0
        self.needs_pgo = False
        self._request_id = 0
        self._last_accept_count = -(10**9)
        self._pending: _Pending | None = None
        self._last_correction: LoopCorrection | None = None
        self.observations: dict[int, KeyframeObservations] = {}  # for the global adjustment
        self.global_ba: GlobalBaResult | None = None
        self.images: dict[int, np.ndarray] = {}  # left image per keyframe (patch refinement)
        self._odometry_edge_cache: dict[int, tuple[np.ndarray, np.ndarray, PoseEdge]] = {}
        """Per keyframe: its edge from the previous one, with the two poses it was made from
        (held here, so an identity test tells whether either was replaced)."""
        self.inertial: dict[int, KeyframeInertial] = {}
        """Keyframe id -> the back end's final inertial state, in its odometry world (set by
        the stage at the end with ``global_ba_imu``): the global adjustment's IMU factors."""
        self.exclude_from_adjustment: set[int] = set()
        """Keyframes left out of the global adjustment (set by the stage at the end: those the
        back end never smoothed, i.e. from before its initialisation)."""

    # ------------------------------------------------------------------ poses
    def _root(self, seg: int) -> int:
        while self.component.get(seg, seg) != seg:
            seg = self.component[seg]
        return seg

    def corrected_pose(self, kf_id: int) -> np.ndarray:
        """map_from_body of a keyframe: its PGO pose, else its odometry pose mapped through its
        segment's ``map_from_odom``."""
        pose = self.optimised.get(kf_id)
        if pose is not None:
            return pose
        return self.map_from_odom.get(self.segment_of[kf_id], np.eye(4)) @ self.odom[kf_id]

    def corrected_poses(self) -> dict[int, np.ndarray]:
        return {k: self.corrected_pose(k) for k in self.kf_ids}

    def keyframe_map_from_odom(self) -> dict[int, np.ndarray]:
        """Per keyframe: corrected pose @ inverse(odometry pose) (the correction to apply to
        frames tracked after it)."""
        return {k: self.corrected_pose(k) @ invert_transform(self.odom[k]) for k in self.kf_ids}

    def update_odometry(self, kf_id: int, world_from_body: np.ndarray) -> None:
        """Refresh a keyframe's odometry pose (e.g. the back end optimised it)."""
        if kf_id in self.odom:
            self.odom[kf_id] = np.array(world_from_body, dtype=float)
            self.store.set_odometry(kf_id, world_from_body)

    # ------------------------------------------------------------------ main entry
    def add_keyframe(self, kf: Keyframe, world_from_body_odom: np.ndarray) -> LoopEvent | None:
        """Describe, query, verify, gate; add the keyframe to the graph (and optimise inline
        when ``inline_pgo`` and a loop was accepted)."""
        cpu0 = time.thread_time()
        try:
            return self._add_keyframe(kf, world_from_body_odom, cpu0)
        finally:
            self.stats.keyframe_cpu_ms.append((time.thread_time() - cpu0) * 1e3)

    def _add_keyframe(
        self, kf: Keyframe, world_from_body_odom: np.ndarray, cpu: float
    ) -> LoopEvent | None:
        t0 = time.perf_counter()
        desc = describe_keyframe(
            kf,
            kf.world_from_body_vo,
            self.body_from_cam0,
            self.vocab,
            self.intr,
            self.cfg.max_orb_features,
            self.orb,
        )
        self.stats.describe_ms.append((time.perf_counter() - t0) * 1e3)
        cpu = self.stats.add_cpu("describe", cpu)
        self._add_node(kf, world_from_body_odom)
        self.store.add_description(desc, world_from_body_odom)
        if self.cfg.patch_refinement:
            self.images[kf.keyframe_id] = kf.image_left
        if self.cfg.global_ba:
            self.observations[kf.keyframe_id] = self._observations(kf)
        # covisible: the keyframes since the oldest start of the landmark tracks that go on
        # from the previous keyframe; a landmark seen again after a gap (the front end found
        # it in its map) starts a new track, so a revisit stays a loop
        prev_kf = self.prev_in_segment.get(kf.keyframe_id)
        covisible_from = kf.keyframe_id
        seen_first: dict[int, int] = {}  # older keyframe -> its landmarks seen here
        tracked_too = self.cfg.covisibility_edges == "tracked"
        for lid in np.asarray(kf.landmark_ids).tolist():
            lid = int(lid)
            first = self.first_kf_of_landmark.setdefault(lid, kf.keyframe_id)
            found_again = prev_kf is None or self.last_kf_of_landmark.get(lid) != prev_kf
            if first != kf.keyframe_id and (found_again or tracked_too):
                seen_first[first] = seen_first.get(first, 0) + 1
            if found_again:
                self.track_start_of_landmark[lid] = kf.keyframe_id
            covisible_from = min(covisible_from, self.track_start_of_landmark[lid])
            self.last_kf_of_landmark[lid] = kf.keyframe_id
        seg = kf.segment_id
        if self.cfg.covisibility_edges != "off" and seen_first:
            self._add_covisibility_edge(kf, desc, seen_first)

        def exclude(other: int) -> bool:  # covisible: same segment, shares tracked landmarks
            return self.segment_of.get(other) == seg and other >= covisible_from

        t1 = time.perf_counter()
        with self.store.lock:
            detection = self.detector.process(kf.keyframe_id, kf.t_ns, desc.bow, exclude=exclude)
        self.stats.query_ms.append((time.perf_counter() - t1) * 1e3)
        cpu = self.stats.add_cpu("query", cpu)
        self.stats.keyframes += 1
        if detection is None:
            return None
        self.stats.detections += 1
        if self.stats.keyframes - self._last_accept_count <= self.cfg.min_keyframes_between_loops:
            return None
        candidates = [detection.match_kf_id] + [
            k for k in detection.island_kf_ids if k != detection.match_kf_id
        ]
        event = self._verify_and_gate(kf, desc, candidates[: self.cfg.candidates_to_verify])
        if event.status == "accepted" and self.inline_pgo:
            cpu = time.thread_time()
            outcome = run_pgo(self.pgo_request())
            correction = self.apply_pgo(outcome)
            self.stats.add_cpu("pgo", cpu)
            event = LoopEvent(**{**event.__dict__, "correction": correction})
        return event

    def _add_node(self, kf: Keyframe, world_from_body_odom: np.ndarray) -> None:
        k, seg = int(kf.keyframe_id), int(kf.segment_id)
        pose = np.array(world_from_body_odom, dtype=float)
        self.kf_ids.append(k)
        self.segment_of[k] = seg
        self.t_ns_of[k] = int(kf.t_ns)
        self.odom[k] = pose
        self.component.setdefault(seg, seg)
        prev = self.last_of_segment.get(seg)
        if prev is not None:
            self.prev_in_segment[k] = prev
            step = float(np.linalg.norm(pose[:3, 3] - self.odom[prev][:3, 3]))
            self.path_m[k] = self.path_m[prev] + step
        else:
            self.path_m[k] = 0.0
        self.last_of_segment[seg] = k

    def _add_covisibility_edge(
        self, kf: Keyframe, desc: KeyframeDescription, seen_first: dict[int, int]
    ) -> None:
        """An edge to the keyframe at least ``covisibility_min_gap_s`` older that first saw
        the largest number of this keyframe's landmarks (the front end tracks them again:
        map reuse), its relative pose fitted on patches from the odometry's
        (``verify.refine_on_patches``, as a loop edge): the pose graph then holds the tie to
        the old map that map reuse gives the odometry, and a loop correction no longer pulls
        against it. Nothing when the fit fails or moves the odometry's relative pose by more
        than ``patch_max_change_*``."""
        c = self.cfg
        q = kf.keyframe_id
        seg = self.segment_of[q]
        min_gap_ns = int(c.covisibility_min_gap_s * 1e9)
        older = [
            (n, k)
            for k, n in seen_first.items()
            if n >= c.covisibility_min_landmarks
            and self.segment_of.get(k) == seg
            and self.t_ns_of[q] - self.t_ns_of[k] >= min_gap_ns
            and k in self.images
            and self.store.has(k)
        ]
        if not older:
            return
        t0 = time.perf_counter()
        _, match = max(older)
        odom_rel = invert_transform(self.odom[match]) @ self.odom[q]
        guess = self.cam0_from_body @ odom_rel @ self.body_from_cam0
        cand = self.store.description(match)
        ref = refine_on_patches(
            guess,
            self.intr,
            self.images[match],
            cand.landmark_xy_undist,
            cand.landmark_points_cam,
            kf.image_left,
            desc.landmark_xy_undist,
            desc.landmark_points_cam,
        )
        self.stats.covisibility_attempts += 1
        self.stats.covisibility_ms.append((time.perf_counter() - t0) * 1e3)
        if ref is None:
            return
        change = invert_transform(guess) @ ref.candidate_cam_from_query_cam
        if (
            np.linalg.norm(change[:3, 3]) > c.patch_max_change_m
            or np.degrees(rotation_angle_rad(change[:3, :3])) > c.patch_max_change_deg
        ):
            return
        measured = self.body_from_cam0 @ ref.candidate_cam_from_query_cam @ self.cam0_from_body
        self.covisibility_edges.append(
            PoseEdge(match, q, measured, self._body_information(ref.information))
        )
        self.stats.covisibility_edges += 1

    def _body_information(self, cam_information: np.ndarray) -> np.ndarray:
        """A patch fit's information (cam0 frame) moved to the body frame, times
        ``patch_information_scale``."""
        # delta_body = Ad(body_from_cam0) delta_cam (right perturbations, translation first)
        rot, pos = self.body_from_cam0[:3, :3], self.body_from_cam0[:3, 3]
        adj = np.block([[rot, skew(pos) @ rot], [np.zeros((3, 3)), rot]])
        adj_inv = np.linalg.inv(adj)
        info = adj_inv.T @ cam_information @ adj_inv * self.cfg.patch_information_scale
        return 0.5 * (info + info.T)

    # ------------------------------------------------------------------ verification
    def _verify(
        self, desc: KeyframeDescription, candidates: list[int]
    ) -> tuple[int, LoopVerification | None, str]:
        """The best-verified candidate: (id, verification, method). Landmark to landmark
        first (accurate, see ``verify_loop_landmarks``); the query's whole-image ORB keypoints
        against the candidate's landmarks only when no candidate passes that way."""
        best: tuple[int, LoopVerification | None, str] = (-1, None, "")
        for method in ("landmarks", "orb"):
            for cand in candidates:
                if not self.store.has(cand):
                    continue
                c = self.store.description(cand)
                if method == "landmarks":
                    res = self._verify_landmark_to_landmark(desc, c)
                else:
                    res = verify_loop(
                        desc.query_xy_undist,
                        desc.query_desc,
                        c.landmark_desc,
                        c.landmark_points_cam,
                        self.K,
                        None,
                        self.verify_params,
                    )
                if res is not None and (best[1] is None or res.num_inliers > best[1].num_inliers):
                    best = (cand, res, method)
            if best[1] is not None:
                break
        return best

    def _verify_landmark_to_landmark(
        self, query: KeyframeDescription, candidate: KeyframeDescription
    ) -> LoopVerification | None:
        """``verify_loop_landmarks`` between two keyframe descriptions (None when either lacks
        the front end's pixels for its landmark descriptors)."""
        if len(query.landmark_xy_undist) != len(query.landmark_desc) or len(
            candidate.landmark_xy_undist
        ) != len(candidate.landmark_desc):
            return None
        return verify_loop_landmarks(
            query.landmark_xy_undist,
            query.landmark_desc,
            query.landmark_points_cam,
            candidate.landmark_xy_undist,
            candidate.landmark_desc,
            candidate.landmark_points_cam,
            self.K,
            self.verify_params,
        )

    def _refine_on_patches(
        self, kf: Keyframe, desc: KeyframeDescription, match: int, ver: LoopVerification
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """The landmark-verified pose refined on patches (``verify.refine_on_patches``) and its
        information in the body frame (g2o order, times ``patch_information_scale``); the
        verified pose and None when the refinement fails or moves it implausibly far."""
        image = self.images.get(match)
        if image is None:
            return ver.candidate_cam_from_query_cam, None
        cand = self.store.description(match)
        ref = refine_on_patches(
            ver.candidate_cam_from_query_cam,
            self.intr,
            image,
            cand.landmark_xy_undist,
            cand.landmark_points_cam,
            kf.image_left,
            desc.landmark_xy_undist,
            desc.landmark_points_cam,
        )
        if ref is None:
            return ver.candidate_cam_from_query_cam, None
        change = (
            invert_transform(ver.candidate_cam_from_query_cam) @ ref.candidate_cam_from_query_cam
        )
        if (
            np.linalg.norm(change[:3, 3]) > self.cfg.patch_max_change_m
            or np.degrees(rotation_angle_rad(change[:3, :3])) > self.cfg.patch_max_change_deg
        ):
            return ver.candidate_cam_from_query_cam, None
        self.stats.patch_refined += 1
        return ref.candidate_cam_from_query_cam, self._body_information(ref.information)

    def _verify_and_gate(
        self, kf: Keyframe, desc: KeyframeDescription, candidates: list[int]
    ) -> LoopEvent:
        q = kf.keyframe_id
        t0, cpu = time.perf_counter(), time.thread_time()
        match, ver, method = self._verify(desc, candidates)
        self.stats.verify_ms.append((time.perf_counter() - t0) * 1e3)
        cpu = self.stats.add_cpu("verify", cpu)
        if ver is None:
            self.stats.rejected_verification += 1
            return LoopEvent(kf.t_ns, q, candidates[0], "rejected", "verification failed", 0)
        self.stats.verified += 1
        cand_from_query, information = ver.candidate_cam_from_query_cam, None
        if method == "landmarks" and self.cfg.patch_refinement:
            cand_from_query, information = self._refine_on_patches(kf, desc, match, ver)
            self.stats.add_cpu("refine", cpu)
        measured = self.body_from_cam0 @ cand_from_query @ self.cam0_from_body
        pairs = None
        if method == "landmarks":
            pairs = np.stack(
                [
                    desc.landmark_ids[ver.query_indices],
                    self.store.description(match).landmark_ids[ver.candidate_indices],
                ],
                axis=1,
            )
        record = LoopRecord(
            loop_id=-1,  # numbered when accepted
            query_kf_id=q,
            match_kf_id=match,
            match_body_from_query_body=measured,
            inliers=ver.num_inliers,
            t_ns=kf.t_ns,
            method=method,
            landmark_pairs=pairs,
            information=information,
        )
        implied_query = self.corrected_pose(match) @ measured
        current_query = self.corrected_pose(q)
        jump_m = float(np.linalg.norm(implied_query[:3, 3] - current_query[:3, 3]))
        jump_deg = float(
            np.degrees(rotation_angle_rad(current_query[:3, :3].T @ implied_query[:3, :3]))
        )
        q_seg, m_seg = self.segment_of[q], self.segment_of[match]
        c = self.cfg
        if q_seg == m_seg:
            path = self.path_m[q] - self.path_m[match]
            max_m = c.gate_base_m + c.gate_ratio * path
            max_deg = c.gate_base_deg + c.gate_deg_per_m * path
            if jump_m > max_m or jump_deg > max_deg:
                self.stats.rejected_gate += 1
                return LoopEvent(
                    kf.t_ns,
                    q,
                    match,
                    "rejected",
                    f"implausible correction {jump_m:.2f} m / {jump_deg:.1f} deg after "
                    f"{path:.1f} m of path (max {max_m:.2f} m / {max_deg:.1f} deg)",
                    ver.num_inliers,
                )
            return self._accept([record], kf.t_ns)
        # Between segments: no odometry to gate with; a second agreeing loop confirms.
        alignment = implied_query @ invert_transform(current_query)
        pend = self._pending
        if (
            pend is not None
            and {pend.query_seg, pend.match_seg} == {q_seg, m_seg}
            and self.stats.keyframes - pend.kf_count <= c.confirm_within_keyframes
        ):
            if pend.query_seg != q_seg:
                alignment = invert_transform(alignment)
            diff = invert_transform(pend.map_from_query_map) @ alignment
            if (
                np.linalg.norm(diff[:3, 3]) <= c.confirm_translation_m
                and np.degrees(rotation_angle_rad(diff[:3, :3])) <= c.confirm_rotation_deg
            ):
                self._pending = None
                return self._accept([pend.record, record], kf.t_ns)
            self.stats.rejected_unconfirmed += 1
        elif pend is not None:
            self.stats.rejected_unconfirmed += 1
        self._pending = _Pending(record, q_seg, m_seg, alignment, self.stats.keyframes)
        return LoopEvent(
            kf.t_ns, q, match, "pending", "waiting for a confirming loop", ver.num_inliers
        )

    def add_loop_constraint(
        self,
        query_kf_id: int,
        match_kf_id: int,
        match_body_from_query_body: np.ndarray,
        inliers: int = 0,
    ) -> LoopEvent:
        """Add a loop edge without verification or gates (external constraints, tests); the
        robust kernel is then the only guard."""
        record = LoopRecord(
            len(self.loops),
            query_kf_id,
            match_kf_id,
            np.array(match_body_from_query_body, dtype=float),
            inliers,
            self.t_ns_of[query_kf_id],
        )
        event = self._accept([record], record.t_ns, count=False)
        if self.inline_pgo:
            correction = self.apply_pgo(run_pgo(self.pgo_request()))
            event = LoopEvent(**{**event.__dict__, "correction": correction})
        return event

    def _accept(self, records: list[LoopRecord], t_ns: int, count: bool = True) -> LoopEvent:
        for rec in records:
            rec.loop_id = len(self.loops)
            a, b = (
                self._root(self.segment_of[rec.query_kf_id]),
                self._root(self.segment_of[rec.match_kf_id]),
            )
            if a != b:
                self._merge_components(rec)
            self.loops.append(rec)
            if count:
                self.stats.accepted += 1
        self._last_accept_count = self.stats.keyframes
        self.needs_pgo = True
        last = records[-1]
        return LoopEvent(
            t_ns,
            last.query_kf_id,
            last.match_kf_id,
            "accepted",
            "",
            last.inliers,
            tuple(r.loop_id for r in records),
        )

    def _merge_components(self, rec: LoopRecord) -> None:
        """Link two components: move the newer one onto the older by the loop's alignment so
        the optimiser starts close to the answer."""
        q_root = self._root(self.segment_of[rec.query_kf_id])
        m_root = self._root(self.segment_of[rec.match_kf_id])
        implied_query = self.corrected_pose(rec.match_kf_id) @ rec.match_body_from_query_body
        # alignment maps the query component's map frame onto the match component's
        align = implied_query @ invert_transform(self.corrected_pose(rec.query_kf_id))
        older_is_match = min(self._members(m_root)) < min(self._members(q_root))
        moved_root, kept_root = (q_root, m_root) if older_is_match else (m_root, q_root)
        if not older_is_match:
            align = invert_transform(align)
        for seg in [s for s in self.component if self._root(s) == moved_root]:
            self.map_from_odom[seg] = align @ self.map_from_odom.get(seg, np.eye(4))
        for k in self.kf_ids:
            if k in self.optimised and self._root(self.segment_of[k]) == moved_root:
                self.optimised[k] = align @ self.optimised[k]
        self.component[moved_root] = kept_root

    def _members(self, root: int) -> list[int]:
        return [k for k in self.kf_ids if self._root(self.segment_of[k]) == root]

    # ------------------------------------------------------------------ optimisation
    def pgo_request(self) -> PgoRequest:
        """The pose graph of the component holding the newest accepted loop."""
        c = self.cfg
        active = [r for r in self.loops if r.active]
        if not active:
            raise ValueError("no loop to optimise")
        root = self._root(self.segment_of[active[-1].query_kf_id])
        nodes = self._members(root)
        node_set = set(nodes)
        poses = {k: self.corrected_pose(k) for k in nodes}
        odo = self._odometry_edges(nodes) + [
            e for e in self.covisibility_edges if e.from_id in node_set and e.to_id in node_set
        ]
        loops = [r for r in active if r.query_kf_id in node_set and r.match_kf_id in node_set]
        self._request_id += 1
        self.needs_pgo = False
        return PgoRequest(
            request_id=self._request_id,
            world_from_node=poses,
            odometry_edges=tuple(odo),
            loop_edges=tuple(
                PoseEdge(
                    r.match_kf_id,
                    r.query_kf_id,
                    r.match_body_from_query_body,
                    loop_information(r.method, c, r.information),
                )
                for r in loops
            ),
            loop_ids=tuple(r.loop_id for r in loops),
            fixed_id=min(nodes),
            robust=c.robust,
            robust_threshold=robust_threshold(c),
        )

    def _odometry_edges(self, nodes: list[int]) -> list[PoseEdge]:
        """Odometry edges between consecutive keyframes of a segment, among ``nodes``.

        Each edge is cached with the two odometry poses it was made from and made again only
        when either was replaced (``update_odometry`` refreshes the newest few): built afresh
        for every pose graph, they took ~30 ms of each optimisation on room-aggressive."""
        odo: list[PoseEdge] = []
        for k in nodes:
            prev = self.prev_in_segment.get(k)
            if prev is None:
                continue
            a, b = self.odom[prev], self.odom[k]
            cached = self._odometry_edge_cache.get(k)
            if cached is not None and cached[0] is a and cached[1] is b:
                odo.append(cached[2])
                continue
            rel = invert_transform(a) @ b
            dt_s = (self.t_ns_of[k] - self.t_ns_of[prev]) * 1e-9
            sigma_m, sigma_rad = odometry_sigmas(rel, dt_s, self.cfg)
            edge = PoseEdge(prev, k, rel, information_from_sigmas(sigma_m, sigma_rad))
            self._odometry_edge_cache[k] = (a, b, edge)
            odo.append(edge)
        return odo

    def _observations(self, kf: Keyframe) -> KeyframeObservations:
        """The keyframe's observations, landmarks moved into its cam0 frame."""
        cam_from_world = invert_transform(
            np.asarray(kf.world_from_body_vo, dtype=float) @ self.body_from_cam0
        )
        pts = np.asarray(kf.points_world_vo, dtype=float).reshape(-1, 3)
        return KeyframeObservations(
            landmark_ids=np.asarray(kf.landmark_ids, dtype=np.int64).copy(),
            left_px=np.asarray(kf.pixels_left_undist, dtype=float).copy(),
            right_px=np.asarray(kf.pixels_right_undist, dtype=float).copy(),
            points_cam0=pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3],
        )

    def _set_optimised(self, world_from_body: dict[int, np.ndarray]) -> None:
        """Take optimised keyframe poses; each segment's ``map_from_odom`` from its newest
        optimised keyframe; a new map generation."""
        newest: dict[int, int] = {}
        for k, pose in world_from_body.items():
            self.optimised[k] = np.array(pose, dtype=float)
            seg = self.segment_of[k]
            if k > newest.get(seg, -1):
                newest[seg] = k
        for seg, k in newest.items():
            self.map_from_odom[seg] = self.optimised[k] @ invert_transform(self.odom[k])
        self.map_generation += 1
        self.store.set_corrected(self.corrected_poses())

    def global_adjustment_budget_s(self, keyframe_ids: Iterable[int] | None = None) -> float | None:
        """The global adjustment's whole time budget (s; None: no limit): its fraction of the
        time ``keyframe_ids`` span (default: every keyframe)."""
        fraction = self.cfg.global_ba_budget_fraction
        times = [self.t_ns_of[k] for k in (self.t_ns_of if keyframe_ids is None else keyframe_ids)]
        if fraction <= 0 or not times:
            return None
        return fraction * (max(times) - min(times)) * 1e-9

    def global_adjustment(self, spent_s: float = 0.0) -> GlobalBaResult | None:
        """Global bundle adjustment (:mod:`slam.loop.global_ba`) of the component holding the
        newest active loop, starting from the pose graph's result; its keyframe poses replace
        the corrected ones. None (nothing changed) without an active loop or when disabled.
        ``spent_s``: time the end of the run has already used (the loop backlog), taken off
        the time budget."""
        active = [r for r in self.loops if r.active]
        if not self.cfg.global_ba or not active:
            return None
        root = self._root(self.segment_of[active[-1].query_kf_id])
        # Keyframes from before the back end's initialisation have no smoothed odometry, and
        # their edge to the next carries the change of frame: measured on room-figure8, leaving
        # out keyframes 0 and 1 took the others' ATE after the adjustment from 3.1 to 2.7 mm
        # (the first 5 s from 5.0 to 2.4 mm). They keep their pose-graph pose.
        nodes = [k for k in self._members(root) if k not in self.exclude_from_adjustment]
        if len(nodes) < 2:
            return None
        node_set = set(nodes)
        pairs = [
            (r.query_kf_id, int(a), r.match_kf_id, int(b))
            for r in active
            if r.landmark_pairs is not None
            and r.query_kf_id in node_set
            and r.match_kf_id in node_set
            for a, b in r.landmark_pairs.tolist()
        ]
        c = self.cfg
        t0, cpu = time.perf_counter(), time.thread_time()
        budget_s = self.global_adjustment_budget_s(nodes)
        if budget_s is not None:
            budget_s = max(budget_s - spent_s, 0.0)
        fusion_pairs = searched = 0
        if c.global_ba_fusion:
            share = None if budget_s is None else c.global_ba_fusion_budget_share * budget_s
            found, searched = self._fusion_pairs(nodes, None if share is None else t0 + share)
            fusion_pairs = len({(qk, mk) for qk, _, mk, _ in found})
            pairs += found
        fusion_s = time.perf_counter() - t0
        cpu = self.stats.add_cpu("fusion", cpu)
        if budget_s is not None:
            budget_s = max(budget_s - fusion_s, 0.0)
        inertial = None
        if c.global_ba_imu and self.inertial and self.calib.imu is not None:
            # velocities into the corrected frame: each keyframe's correction's rotation
            inertial = {
                k: s.with_state(
                    (self.corrected_pose(k)[:3, :3] @ self.odom[k][:3, :3].T)
                    @ s.velocity_world_m_s,
                    s.bias_gyro_rad_s,
                    s.bias_accel_m_s2,
                )
                for k, s in self.inertial.items()
                if k in node_set and k in self.odom
            }
        result = global_bundle_adjustment(
            self.calib,
            self.observations,
            {k: self.corrected_pose(k) for k in nodes},
            self._odometry_edges(nodes),
            pairs,
            fixed_id=min(nodes),
            keyframe_t_ns=self.t_ns_of,
            params=GlobalBaParams(
                pixel_sigma_px=c.global_ba_pixel_sigma_px,
                outlier_sigmas=c.global_ba_outlier_sigmas,
                rounds=c.global_ba_rounds,
                keyframe_sigma_max=c.global_ba_keyframe_sigma_max,
                odometry_sigma_scale=c.global_ba_odometry_sigma_scale,
                time_budget_s=budget_s,
                max_keyframes_per_landmark=c.global_ba_max_keyframes_per_landmark,
                thin_by=c.global_ba_thin_by,
                max_observations_per_landmark=c.global_ba_max_observations_per_landmark,
                imu_midpoint_rotation=c.global_ba_imu_midpoint,
                imu_odometry_rotation_only=c.global_ba_imu_odometry_rotation_only,
                imu_accel_walk_factor=c.global_ba_imu_accel_walk_factor,
                imu_gyro_walk_factor=c.global_ba_imu_gyro_walk_factor,
                imu_walk_gate=c.global_ba_imu_walk_gate,
                imu_accel_bias_smoothing=c.global_ba_imu_accel_bias_smoothing,
                imu_refit_max_std=c.global_ba_imu_refit_max_std,
            ),
            inertial=inertial,
            imu=self.calib.imu,
        )
        self.stats.add_cpu("adjustment", cpu)
        if result is None:
            return None
        result = dataclasses.replace(
            result,
            fusion_keyframe_pairs=fusion_pairs,
            fusion_keyframes_searched=searched,
            fusion_seconds=fusion_s,
        )
        self._set_optimised(result.world_from_body)
        self.global_ba = result
        return result

    def _fusion_pairs(
        self, nodes: list[int], deadline: float | None = None
    ) -> tuple[list[tuple[int, int, int, int]], int]:
        """Landmark pairs (keyframe, landmark, keyframe, landmark) between each keyframe and
        up to ``global_ba_fusion_candidates`` older keyframes of other passes near its
        corrected pose (one per pass), matched landmark to landmark like a loop and kept only
        when the match's relative pose agrees with the corrected poses (ORB-SLAM's loop
        fusion: the revisit then shares landmarks with the first pass everywhere, not only at
        the few keyframes where a loop was accepted).

        With a ``deadline`` (``time.perf_counter``) the search stops there, having visited
        the keyframes in an order that spreads over the run (every 8th first, then the ones
        between), so a cut search still fuses every part of the map."""
        c = self.cfg
        ids = [k for k in sorted(nodes) if self.store.has(k)]
        if len(ids) < 2:
            return [], 0
        world_from_cam = np.array([self.corrected_pose(k) @ self.body_from_cam0 for k in ids])
        pos = world_from_cam[:, :3, 3]
        view = world_from_cam[:, :3, 2]
        t_s = np.array([self.t_ns_of[k] for k in ids], dtype=float) * 1e-9
        cos_max = np.cos(np.radians(c.global_ba_fusion_angle_deg))
        out: list[tuple[int, int, int, int]] = []
        searched = 0
        for i in sorted(range(len(ids)), key=lambda i: (i % 8, i)):
            if deadline is not None and time.perf_counter() > deadline:
                break
            searched += 1
            q = ids[i]
            older = np.flatnonzero(t_s < t_s[i] - c.global_ba_fusion_min_gap_s)
            if not len(older):
                continue
            dist = np.linalg.norm(pos[older] - pos[i], axis=1)
            cos = view[older] @ view[i]
            ok = (dist <= c.global_ba_fusion_radius_m) & (cos >= cos_max)
            older, dist, cos = older[ok], dist[ok], cos[ok]
            score = dist / c.global_ba_fusion_radius_m + (1.0 - cos) / (1.0 - cos_max)
            chosen: list[int] = []
            for j in older[np.argsort(score, kind="stable")].tolist():
                if len(chosen) >= c.global_ba_fusion_candidates:
                    break
                if any(abs(t_s[j] - t_s[o]) < c.global_ba_fusion_min_gap_s for o in chosen):
                    continue  # one candidate per pass
                chosen.append(j)
            qd = self.store.description(q)
            for j in chosen:
                m = ids[j]
                md = self.store.description(m)
                ver = self._verify_landmark_to_landmark(qd, md)
                if ver is None:
                    continue
                measured = (
                    self.body_from_cam0 @ ver.candidate_cam_from_query_cam @ self.cam0_from_body
                )
                expected = invert_transform(self.corrected_pose(m)) @ self.corrected_pose(q)
                diff = invert_transform(expected) @ measured
                if (
                    np.linalg.norm(diff[:3, 3]) > c.global_ba_fusion_gate_m
                    or np.degrees(rotation_angle_rad(diff[:3, :3])) > c.global_ba_fusion_gate_deg
                ):
                    continue
                qa = qd.landmark_ids[ver.query_indices].tolist()
                mb = md.landmark_ids[ver.candidate_indices].tolist()
                out += [(q, int(a), m, int(b)) for a, b in zip(qa, mb, strict=True)]
        return out, searched

    def apply_pgo(self, outcome: PgoOutcome) -> LoopCorrection:
        """Take an optimisation's result: new keyframe poses, per-segment ``map_from_odom``
        (from each segment's newest optimised keyframe), loops the kernel rejected switched
        off. Keyframes added since the request follow their segment's new ``map_from_odom``."""
        self.stats.pgo_runs += 1
        self.stats.pgo_ms.append(outcome.seconds * 1e3)
        by_id = {r.loop_id: r for r in self.loops}
        for lid, ok in zip(outcome.loop_ids, outcome.loop_inliers.tolist(), strict=True):
            if not ok and by_id[lid].active:
                by_id[lid].active = False
                self.stats.rejected_by_pgo += 1
        poses = outcome.world_from_node
        if self.cfg.pgo_align_to_odometry and len(poses) >= 3:
            gauge = _rigid_fit(
                np.array([p[:3, 3] for p in poses.values()]),
                np.array([self.odom[k][:3, 3] for k in poses]),
            )
            poses = {k: gauge @ p for k, p in poses.items()}
        self._set_optimised(poses)
        last = max((r for r in self.loops if r.active), key=lambda r: r.loop_id, default=None)
        correction = LoopCorrection(
            t_ns=self.t_ns_of[self.kf_ids[-1]],
            loop_id=-1 if last is None else last.loop_id,
            query_keyframe_id=-1 if last is None else last.query_kf_id,
            match_keyframe_id=-1 if last is None else last.match_kf_id,
            inliers=0 if last is None else last.inliers,
            map_generation=self.map_generation,
            map_from_odom={s: m.copy() for s, m in self.map_from_odom.items()},
            corrected_keyframe_poses=self.corrected_poses(),
        )
        self._last_correction = correction
        return correction

    @property
    def last_correction(self) -> LoopCorrection | None:
        return self._last_correction

    def loop_edges(self) -> list[LoopRecord]:
        return list(self.loops)

    def graph_dump(self) -> dict[str, object]:
        """The pose graph as plain lists (JSON): per keyframe id, t_ns, segment, odometry and
        corrected poses (x y z qw qx qy qz); per loop, its edge (match_body_from_query_body)."""
        from slam.core.geometry import matrix_to_quat_wxyz

        def vec(pose: np.ndarray) -> list[float]:
            q = matrix_to_quat_wxyz(pose[:3, :3])
            return [float(v) for v in (*pose[:3, 3], *q)]

        return {
            "kf_ids": list(self.kf_ids),
            "t_ns": [self.t_ns_of[k] for k in self.kf_ids],
            "segment": [self.segment_of[k] for k in self.kf_ids],
            "odometry": [vec(self.odom[k]) for k in self.kf_ids],
            "corrected": [vec(self.corrected_pose(k)) for k in self.kf_ids],
            "loops": [
                {
                    "query_kf": r.query_kf_id,
                    "match_kf": r.match_kf_id,
                    "inliers": r.inliers,
                    "active": r.active,
                    "match_body_from_query_body": vec(r.match_body_from_query_body),
                }
                for r in self.loops
            ],
        }


def _rigid_fit(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """The rigid transform (4x4) taking points ``src`` (N, 3) closest to ``dst`` (Umeyama,
    no scale)."""
    ms, md = src.mean(axis=0), dst.mean(axis=0)
    u, _, vt = np.linalg.svd((dst - md).T @ (src - ms))
    fix = np.eye(3)
    fix[2, 2] = np.sign(np.linalg.det(u @ vt))
    rot = u @ fix @ vt
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = md - rot @ ms
    return out


def bridge_corrections(
    world_from_body: np.ndarray,
    corrected_at: np.ndarray,
    segment_ids: np.ndarray,
    max_gap: int = 3,
) -> np.ndarray:
    """The odometry chain ``world_from_body`` (N, 4, 4) with the translation of each
    frame-to-frame motion across a front-end correction (``corrected_at``: indices of the
    first frames tracked in a world the front end had just moved) replaced by the mean of the
    nearest uncorrupted motions before and after it (within ``max_gap`` frames, same segment);
    every later frame moves with it. Undoing a correction's rigid transform
    (:meth:`slam.runtime.recorder.Recorder.continuous_odometry`) is exact only for the part of
    the move that was rigid: map reuse and re-anchoring also make the next frames track
    landmarks that the move did not carry, and the undone chain stepped by up to 14 mm at such
    frames on room-loop (loop-closed frames between keyframes 1.06 mm ATE, keyframes 0.76;
    bridged 0.80; BENCHMARKS.md). Rotations are left as they are."""
    out = np.array(world_from_body, dtype=float, copy=True)
    n = len(out)
    if n < 3 or len(corrected_at) == 0:
        return out
    seg = np.asarray(segment_ids)
    bad = np.zeros(n, dtype=bool)  # bad[i]: the motion from frame i - 1 to i is corrupted
    bad[np.asarray(corrected_at, dtype=np.int64)[(corrected_at > 0) & (corrected_at < n)]] = True
    bad[0] = True
    bad[1:] |= seg[1:] != seg[:-1]  # no motion across a segment boundary
    motion = np.zeros((n, 3))
    motion[1:] = out[1:, :3, 3] - out[:-1, :3, 3]
    # vectorised (this runs at every output flush, in the main thread): for each corrupted
    # motion, the nearest clean one before it and after it
    index = np.arange(n)
    last_clean = np.maximum.accumulate(np.where(bad, -1, index))
    next_clean = np.minimum.accumulate(np.where(bad, n, index)[::-1])[::-1]
    i = np.flatnonzero(bad[1:-1]) + 1
    before, after = last_clean[i - 1], next_clean[i + 1]
    ok = (before >= 1) & (before >= i - max_gap) & (after < n) & (after <= i + max_gap)
    i, before, after = i[ok], before[ok], after[ok]
    ok = (seg[i] == seg[i - 1]) & (seg[before] == seg[i]) & (seg[after] == seg[i])
    i, before, after = i[ok], before[ok], after[ok]
    step = np.zeros((n, 3))
    step[i] = 0.5 * (motion[before] + motion[after]) - motion[i]
    out[:, :3, 3] += np.cumsum(step, axis=0)
    return out


def loop_closed_poses(
    frame_t_ns: np.ndarray,
    frame_segment_ids: np.ndarray,
    frame_world_from_body: np.ndarray,
    keyframe_t_ns: np.ndarray,
    keyframe_segment_ids: np.ndarray,
    keyframe_map_from_odom: np.ndarray,
    interpolate: bool = True,
) -> np.ndarray:
    """Map every frame's odometry pose through its segment's keyframe corrections.

    With ``interpolate`` a frame between two keyframes of its segment takes the correction
    interpolated in time between theirs (rotation along the geodesic, translation linearly);
    otherwise, and before the first / after the last keyframe, the correction of the latest
    keyframe at or before it (the first one before it). Why interpolate: the corrections of
    consecutive keyframes differ by the smoothing the adjustment did, and holding each one
    until the next keyframe left a step there (measured on room-figure8 after the global
    adjustment: frames 4.6 mm ATE, keyframes 3.1 mm).

    Arrays: frames (N,), (N,), (N, 4, 4); keyframes (M,), (M,), (M, 4, 4) correction =
    corrected keyframe pose @ inverse(its odometry pose). Returns (N, 4, 4).
    """
    out = np.array(frame_world_from_body, dtype=float, copy=True)
    kt = np.asarray(keyframe_t_ns, dtype=np.int64)
    ks = np.asarray(keyframe_segment_ids)
    corr = np.asarray(keyframe_map_from_odom, dtype=float)
    ft = np.asarray(frame_t_ns, dtype=np.int64)
    for seg in np.unique(frame_segment_ids):
        fm = np.flatnonzero(frame_segment_ids == seg)
        km = np.flatnonzero(ks == seg)
        if not len(km):
            continue
        order = km[np.argsort(kt[km], kind="stable")]
        times, seg_corr, f_t = kt[order], corr[order], ft[fm]
        pos = np.clip(np.searchsorted(times, f_t, side="right") - 1, 0, len(order) - 1)
        frame_corr = seg_corr[pos]
        # between two keyframes: vectorised (this runs at every output flush of a run)
        between = (pos + 1 < len(order)) & (times[pos] <= f_t) & interpolate
        if between.any():
            i = pos[between]
            a, b = seg_corr[i], seg_corr[i + 1]
            alpha = (f_t[between] - times[i]) / np.maximum(times[i + 1] - times[i], 1)
            rel = so3_log(np.transpose(a[:, :3, :3], (0, 2, 1)) @ b[:, :3, :3]).reshape(-1, 3)
            rot = a[:, :3, :3] @ so3_exp_batch(alpha[:, None] * rel)
            trans = (1.0 - alpha)[:, None] * a[:, :3, 3] + alpha[:, None] * b[:, :3, 3]
            frame_corr[between, :3, :3] = rot
            frame_corr[between, :3, 3] = trans
        out[fm] = frame_corr @ out[fm]
    return out
