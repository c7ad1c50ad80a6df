"""The dense mapper's core: keyframes with poses in, depth per keyframe, TSDF fusion, mesh out.

A plain class, so the lead can wrap it in a pipeline stage (ideally in a worker process: the
constructor arguments and every input are picklable: numpy arrays and frozen dataclasses).

Per keyframe (:meth:`DenseMapper.add_keyframe`):

1. undistort the images (calibration distortion, ``cv2.initUndistortRectifyMap``);
2. depth: the sensor depth when given (RGB-D); else, with ``depth_method = "sgbm"`` and a
   stereo pair, semi-global matching on the rectified pair (``mapping.stereo_sgbm``: depth in
   the rectified left camera, which is then the keyframe's view); else a plane sweep with the
   stereo partner (``cam1_from_cam0``) and the nearest earlier keyframes by pose (baseline and
   viewing-angle limits) as source views;
3. plane sweep only: filter against the previous keyframe's depth map (multi-view
   consistency): pixels that can be checked and disagree are dropped (SGBM depth is left-right
   checked instead);
4. integrate into the sparse TSDF; the depth map is kept (float16) for re-integration.

Loop correction (:meth:`DenseMapper.update_poses`): keyframes whose pose moved by more than a
threshold are **re-integrated**: de-integrated with the old pose, then integrated with the new
one (exact for the TSDF and weights because weights are not clamped; colours too with
``keep_color``, else re-integration moves geometry only and voxels keep the colour fused
before: the volume's colour has its own weight, so geometry-only updates never dilute it).
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from mapping.mesh import TriangleMesh, extract_mesh, remove_small_components
from mapping.planesweep import (
    SourceView,
    SweepConfig,
    Undistorter,
    depth_consistency,
    plane_sweep,
)
from mapping.stereo_sgbm import RectifiedStereo, SgbmConfig
from mapping.tsdf import TsdfConfig, TsdfVolume
from slam.core.calibration import Calibration
from slam.core.geometry import invert_transform, rotation_angle_rad


@dataclass(frozen=True)
class MapperConfig:
    """Parameters of :class:`DenseMapper`."""

    tsdf: TsdfConfig = field(default_factory=lambda: TsdfConfig(voxel_m=0.02, max_depth_m=4.0))
    """Fusion volume."""
    sweep: SweepConfig = field(
        default_factory=lambda: SweepConfig(depth_min_m=0.4, depth_max_m=8.0, num_planes=128)
    )
    """Plane sweep per keyframe (128 planes: over 0.4-8 m, 64 planes step ~2 px of stereo
    disparity, too coarse for the parabola refinement; 128 halve the mesh error)."""
    depth_method: str = "sgbm"
    """Depth of a stereo keyframe: "sgbm" (rectified semi-global matching on the pair; earlier
    keyframes only check it) or "sweep" (plane sweep over the pair and earlier keyframes).
    752x480 at full size: SGBM ~10x cheaper at similar depth error (BENCHMARKS.md)."""
    sgbm: SgbmConfig = field(default_factory=SgbmConfig)
    """Semi-global matching (``depth_method = "sgbm"``); its ``scale`` is ``depth_scale``."""
    landmark_min_depth_fraction: float = 0.6
    """With the keyframe's landmark depths given, SGBM searches down to this fraction of the
    nearest landmark's depth (tracked corners are not the nearest surface everywhere)."""
    num_keyframe_sources: int = 1
    """Earlier keyframes used as extra source views (besides the stereo partner)."""
    min_baseline_m: float = 0.04
    """A keyframe closer than this to the reference adds little depth information."""
    max_baseline_m: float = 0.6
    """A keyframe farther than this overlaps too little."""
    max_view_angle_deg: float = 30.0
    """Largest angle between optical axes of a reference and a source keyframe."""
    depth_scale: float = 1.0
    """Sweep (and fuse) at this fraction of the image size: 0.5 is ~4x cheaper; at 2 cm voxels a
    half-resolution 752x480 pixel still covers less than a voxel beyond ~1.5 m."""
    min_motion_m: float = 0.02
    """A keyframe within this distance (and ``min_motion_deg``) of the last fused one adds no
    new view of the scene; it is skipped (fusing it would only re-weight the same errors)."""
    min_motion_deg: float = 2.0
    """Rotation below which a keyframe counts as not moved (see ``min_motion_m``)."""
    history: int = 12
    """How many recent keyframes are kept as source candidates (images are kept for these)."""
    consistency_rel_tol: float = 0.02
    """Plane sweep: drop pixels that disagree with the previous keyframe's depth by more than
    this (relative); 0 disables the check. Not applied to SGBM depth, which is left-right
    checked already: on the synthetic room (20 s, ground-truth poses) the check cost 45 % of
    the keyframe's CPU for the same mesh accuracy (1.28 vs 1.31 cm) and less completion (87.7
    vs 89.6 %; ``tools/bench_mapper_depth``)."""
    reintegrate_translation_m: float = 0.01
    """Re-integrate a keyframe after a pose update that moves it more than this..."""
    reintegrate_rotation_deg: float = 0.5
    """...or rotates it more than this."""
    depth_weight_ref_m: float | None = 1.5
    """Stereo depth noise grows with z^2: fuse each pixel with weight min(1, (ref / z)^2) so
    near observations dominate; None = uniform weights (sensor depth gets uniform weights)."""
    mesh_min_weight: float = 0.3
    """Mesh only where every cube corner has fused weight above this (weights are 1 per
    keyframe up to 1.5 m, (1.5 / z)^2 beyond), which removes thin surfaces that one noisy far
    depth map created; 0 keeps everything observed. On the 60 s synthetic room (81 swept
    keyframes, ground-truth poses, 2 cm voxels; ``tools/bench_mapping``) the mean vertex error
    / completion within 5 cm were 2.44 cm / 92.2 % at 0.2, 1.71 cm / 90.4 % at 0.3 and
    1.24 cm / 85.4 % at 0.5."""
    mesh_min_weight_keyframes: int = 3
    """With fewer fused keyframes than this there is no multi-view support to ask for: the
    mesh then keeps every observed surface (min weight 0) instead of coming out empty (a
    single keyframe seeing walls beyond 2.7 m has weights below 0.3 everywhere)."""
    mesh_min_component_vertices: int = 200
    """Drop connected pieces of the mesh with fewer vertices than this (speckle: at 2 cm voxels
    200 vertices are a patch of ~0.1 m^2); 0 keeps all. On the hall (140 s, 467 keyframes,
    ground-truth poses) this removed 6 % of the vertices, 16k pieces, and took the mean vertex
    error from 2.01 to 1.66 cm (BENCHMARKS.md, "Mapping")."""
    keep_color: bool = False
    """Keep every keyframe's colour image so re-integration also moves colour (1 MB per 752x480
    keyframe); without it re-integration moves geometry only. Depth is always kept (float16,
    0.7 MB per 752x480 keyframe)."""


@dataclass(frozen=True)
class StereoRig:
    """What the mapper needs to know of the cameras (undistorted pinholes after undistortion)."""

    undistort_left: Undistorter
    undistort_right: Undistorter | None
    K_left: np.ndarray
    K_right: np.ndarray | None
    cam1_from_cam0: np.ndarray | None

    @staticmethod
    def from_calibration(calibration: Calibration) -> StereoRig:
        left = Undistorter(calibration.cam0.intrinsics)
        if calibration.is_stereo:
            right = Undistorter(calibration.cameras[1].intrinsics)
            return StereoRig(left, right, left.K, right.K, calibration.cam1_from_cam0())
        return StereoRig(left, None, left.K, None, None)


@dataclass(frozen=True)
class KeyframeReport:
    """What one :meth:`DenseMapper.add_keyframe` did (for logging and lag reports)."""

    t_ns: int
    num_sources: int
    valid_fraction: float  # 0 when skipped
    skipped: bool
    depth_ms: float
    fusion_ms: float
    blocks: int


@dataclass
class _StoredKeyframe:
    t_ns: int
    world_from_view: np.ndarray  # the depth map's camera: cam0, or the rectified left camera
    cam0_from_view: np.ndarray
    K: np.ndarray
    depth_m: np.ndarray  # float16, 0 = invalid
    from_stereo: bool  # depth from the sweep (uncertainty weights) or from a sensor
    color: np.ndarray | None  # uint8 RGB, kept only for re-integration colour
    gray: np.ndarray | None  # uint8, kept for the recent history only


def _to_gray_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3:
        img = (
            img[..., :3].astype(np.float32) @ np.array([0.299, 0.587, 0.114], np.float32)
        ).round()
    return np.clip(img, 0, 255).astype(np.uint8)


def _scaled_K(K: np.ndarray, scale: float) -> np.ndarray:  # noqa: N802 - the usual name
    """Pinhole matrix of an image resized by ``scale`` (pixel centres at integers)."""
    if scale == 1.0:
        return K
    out = K.copy()
    out[0, 0] *= scale
    out[1, 1] *= scale
    out[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    out[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    return out


def _resized(image: np.ndarray, scale: float) -> np.ndarray:
    if scale == 1.0:
        return image
    return cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)


def _to_rgb_u8(image: np.ndarray) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    return img[..., :3].astype(np.uint8)


class DenseMapper:
    """Plane sweep (or sensor depth) + TSDF fusion over keyframes; see the module docstring."""

    def __init__(self, config: MapperConfig | None = None, rig: StereoRig | None = None) -> None:
        self.config = config or MapperConfig()
        self.rig = rig
        self.volume = TsdfVolume(self.config.tsdf)
        self.stereo: RectifiedStereo | None = None
        if (
            self.config.depth_method == "sgbm"
            and rig is not None
            and rig.undistort_right is not None
            and rig.cam1_from_cam0 is not None
        ):
            sgbm = self.config.sgbm
            if sgbm.scale != self.config.depth_scale:
                from dataclasses import replace

                sgbm = replace(sgbm, scale=self.config.depth_scale)
            self.stereo = RectifiedStereo(
                rig.undistort_left.intrinsics,
                rig.undistort_right.intrinsics,
                rig.cam1_from_cam0,
                sgbm,
            )
        elif self.config.depth_method not in ("sgbm", "sweep"):
            raise ValueError(f"depth_method {self.config.depth_method!r}: use sgbm or sweep")
        self._keyframes: dict[int, _StoredKeyframe] = {}
        self._order: list[int] = []
        self.reports: list[KeyframeReport] = []

    @staticmethod
    def from_calibration(
        calibration: Calibration, config: MapperConfig | None = None
    ) -> DenseMapper:
        return DenseMapper(config, StereoRig.from_calibration(calibration))

    @property
    def num_keyframes(self) -> int:
        return len(self._keyframes)

    # --- keyframes -----------------------------------------------------------------------------
    def _select_sources(self, world_from_view: np.ndarray) -> list[_StoredKeyframe]:
        cfg = self.config
        axis = world_from_view[:3, 2]
        centre = world_from_view[:3, 3]
        scored = []
        for t in self._order[-cfg.history :]:
            kf = self._keyframes[t]
            if kf.gray is None:
                continue
            baseline = float(np.linalg.norm(kf.world_from_view[:3, 3] - centre))
            cos_angle = float(np.clip(axis @ kf.world_from_view[:3, 2], -1.0, 1.0))
            angle = np.degrees(np.arccos(cos_angle))
            if (
                cfg.min_baseline_m <= baseline <= cfg.max_baseline_m
                and angle <= cfg.max_view_angle_deg
            ):
                scored.append((baseline, kf))
        scored.sort(key=lambda x: x[0])
        return [kf for _, kf in scored[: cfg.num_keyframe_sources]]

    def add_keyframe(
        self,
        t_ns: int,
        image_left: np.ndarray,
        image_right: np.ndarray | None,
        world_from_cam0: np.ndarray,
        K: np.ndarray | None = None,
        depth_m: np.ndarray | None = None,
        color_rgb: np.ndarray | None = None,
        landmark_depth_range_m: tuple[float, float] | None = None,
    ) -> KeyframeReport:
        """Add one keyframe and fuse it.

        ``image_left``/``image_right``: raw cam0/cam1 images (undistorted here when the mapper
        has a rig). ``K``: the pinhole of ``image_left`` when there is no rig (already
        undistorted images). ``depth_m``: sensor depth registered to the left image (skips the
        sweep). ``color_rgb``: colour for the mesh (defaults to the left image).
        ``landmark_depth_range_m``: the depths of the keyframe's tracked landmarks; SGBM then
        searches no nearer than ``landmark_min_depth_fraction`` of the nearest.
        """
        cfg = self.config
        rig = self.rig
        t0 = time.perf_counter()
        stereo = self.stereo if depth_m is None and image_right is not None else None
        cam0_from_view = np.eye(4) if stereo is None else stereo.cam0_from_rect
        world_from_view = np.asarray(world_from_cam0, float) @ cam0_from_view
        if self._order and self._has_not_moved(world_from_view):
            report = KeyframeReport(t_ns, 0, 0.0, True, 0.0, 0.0, self.volume.num_blocks)
            self.reports.append(report)
            return report
        n_sources = 0
        if stereo is not None:
            assert image_right is not None
            left, right = stereo.rectify(image_left, image_right)
            k_left = stereo.K
            gray = _to_gray_u8(left)
            if color_rgb is not None:
                left = stereo.rectify(color_rgb, image_right)[0]
            color = _to_rgb_u8(left)
            near = None
            if landmark_depth_range_m is not None:
                near = cfg.landmark_min_depth_fraction * float(landmark_depth_range_m[0])
            depth = stereo.depth(gray, _to_gray_u8(right), near)
            n_sources = 1
        else:
            left = rig.undistort_left(image_left) if rig else image_left
            k_left = rig.K_left if rig else K
            if k_left is None:
                raise ValueError("add_keyframe needs K when the mapper has no calibration rig")
            scale = cfg.depth_scale if depth_m is None else 1.0
            k_left = _scaled_K(np.asarray(k_left, float), scale)
            gray = _resized(_to_gray_u8(left), scale)
            color = _resized(_to_rgb_u8(color_rgb if color_rgb is not None else left), scale)
        if depth_m is None and stereo is None:
            sources: list[SourceView] = []
            if image_right is not None and rig is not None and rig.undistort_right is not None:
                assert rig.K_right is not None and rig.cam1_from_cam0 is not None
                right = _resized(_to_gray_u8(rig.undistort_right(image_right)), scale)
                sources.append(SourceView(right, _scaled_K(rig.K_right, scale), rig.cam1_from_cam0))
            for kf in self._select_sources(world_from_view):
                assert kf.gray is not None
                src_from_ref = invert_transform(kf.world_from_view) @ world_from_view
                sources.append(SourceView(kf.gray, kf.K, src_from_ref))
            n_sources = len(sources)
            if sources:
                depth = plane_sweep(gray, k_left, sources, cfg.sweep).depth_m
            else:
                depth = np.zeros(gray.shape, np.float32)
        elif depth_m is not None:
            depth = np.asarray(depth_m, np.float32)
        if stereo is None and depth_m is None and cfg.consistency_rel_tol > 0 and self._order:
            prev = self._keyframes[self._order[-1]]
            prev_from_ref = invert_transform(prev.world_from_view) @ world_from_view
            agree, checked = depth_consistency(
                depth,
                k_left,
                prev.depth_m.astype(np.float32),
                prev.K,
                prev_from_ref,
                cfg.consistency_rel_tol,
            )
            depth = np.where(checked & ~agree, 0.0, depth).astype(np.float32)
        # Fuse exactly what is stored (float16) so that re-integration undoes it exactly.
        depth = depth.astype(np.float16).astype(np.float32)
        t1 = time.perf_counter()
        self.volume.integrate(
            depth, k_left, world_from_view, color, weight_map=self._weights(depth, depth_m is None)
        )
        t2 = time.perf_counter()
        self._keyframes[t_ns] = _StoredKeyframe(
            t_ns,
            world_from_view,
            np.array(cam0_from_view, float),
            np.array(k_left, float),
            depth.astype(np.float16),
            depth_m is None,
            color if cfg.keep_color else None,
            gray,
        )
        self._order.append(t_ns)
        if len(self._order) > cfg.history:  # images of old keyframes are no longer needed
            self._keyframes[self._order[-cfg.history - 1]].gray = None
        report = KeyframeReport(
            t_ns,
            n_sources,
            float((depth > 0).mean()),
            False,
            1e3 * (t1 - t0),
            1e3 * (t2 - t1),
            self.volume.num_blocks,
        )
        self.reports.append(report)
        return report

    def _has_not_moved(self, world_from_view: np.ndarray) -> bool:
        last = self._keyframes[self._order[-1]].world_from_view
        delta = invert_transform(last) @ world_from_view
        angle = float(np.degrees(rotation_angle_rad(delta[:3, :3])))
        return bool(
            np.linalg.norm(delta[:3, 3]) < self.config.min_motion_m
            and angle < self.config.min_motion_deg
        )

    def _weights(self, depth: np.ndarray, from_stereo: bool) -> np.ndarray | None:
        ref = self.config.depth_weight_ref_m
        if ref is None or not from_stereo:
            return None
        return np.minimum(1.0, (ref / np.maximum(depth, 1e-3)) ** 2).astype(np.float32)

    # --- loop correction -----------------------------------------------------------------------
    def update_poses(self, world_from_cam0_by_t: Mapping[int, np.ndarray]) -> int:
        """Apply corrected keyframe poses: re-integrate (de-integrate with the old pose, integrate
        with the new) every keyframe that moved more than the thresholds. Returns how many."""
        cfg = self.config
        moved = 0
        for t_ns, new_pose in world_from_cam0_by_t.items():
            kf = self._keyframes.get(int(t_ns))
            if kf is None:
                continue
            new_pose = np.asarray(new_pose, float) @ kf.cam0_from_view
            delta = invert_transform(kf.world_from_view) @ new_pose
            dt = float(np.linalg.norm(delta[:3, 3]))
            dr = float(np.degrees(rotation_angle_rad(delta[:3, :3])))
            if dt <= cfg.reintegrate_translation_m and dr <= cfg.reintegrate_rotation_deg:
                kf.world_from_view = new_pose
                continue
            depth = kf.depth_m.astype(np.float32)
            wmap = self._weights(depth, kf.from_stereo)
            self.volume.deintegrate(depth, kf.K, kf.world_from_view, kf.color, weight_map=wmap)
            self.volume.integrate(depth, kf.K, new_pose, kf.color, weight_map=wmap)
            kf.world_from_view = new_pose
            moved += 1
        return moved

    # --- outputs -------------------------------------------------------------------------------
    def mesh(self, min_weight: float | None = None) -> TriangleMesh:
        """Marching cubes over the fused volume (``min_weight``: see MapperConfig)."""
        cfg = self.config
        if min_weight is not None:
            mw = min_weight
        elif self.num_keyframes < cfg.mesh_min_weight_keyframes:
            mw = 0.0
        else:
            mw = cfg.mesh_min_weight
        mesh = extract_mesh(self.volume, min_weight=mw)
        return remove_small_components(mesh, cfg.mesh_min_component_vertices)

    def keyframe_depth(self, t_ns: int) -> np.ndarray:
        """The fused depth map (float32 m, 0 = invalid) of a keyframe."""
        return self._keyframes[t_ns].depth_m.astype(np.float32)
