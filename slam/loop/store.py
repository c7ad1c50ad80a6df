"""What the loop closer keeps per keyframe, and the thread-safe store the relocaliser reads.

Per keyframe (:func:`describe_keyframe`):

* **query side**: ORB keypoints of the whole left image (``detect_orb``), their BoW vector and
  their *undistorted* pixel positions (pinhole ``K``, distortion removed), so that PnP works
  with any distortion model;
* **candidate side**: ORB descriptors computed *at the keyframe's landmark observations*, with
  the landmarks' 3-D positions in the keyframe's cam0 frame. The front end's pixels are
  undistorted; they are re-distorted through ``CameraIntrinsics.project`` to the raw image, and
  each gets ORB's intensity-centroid orientation (exactly as ``ORB.detectAndCompute`` computes
  it, :func:`ic_angles_deg`) before ``ORB.compute``, so they match descriptors of a later
  ``detect_orb`` call.

The points come from the same front-end state as the keyframe's VO pose, so
``cam_from_world(vo) @ points_world_vo`` is consistent whatever the world drift.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from slam.core.calibration import CameraIntrinsics
from slam.core.geometry import invert_transform
from slam.core.messages import Keyframe
from slam.loop.database import KeyframeDatabase
from slam.loop.orb import OrbFeatures, detect_orb
from slam.loop.vocabulary import BowVector, Vocabulary

ORB_HALF_PATCH = 15  # OpenCV ORB's HALF_PATCH_SIZE (patchSize 31)


def _orb_circle_mask() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ORB's circular patch (OpenCV ``umax`` construction) and its u/v offset grids."""
    hp = ORB_HALF_PATCH
    umax = [0] * (hp + 2)
    vmax = int(np.floor(hp * np.sqrt(2.0) / 2 + 1))
    vmin = int(np.ceil(hp * np.sqrt(2.0) / 2))
    for v in range(vmax + 1):
        umax[v] = int(round(np.sqrt(hp * hp - v * v)))
    v0 = 0
    for v in range(hp, vmin - 1, -1):  # make the circle symmetric, as OpenCV does
        while umax[v0] == umax[v0 + 1]:
            v0 += 1
        umax[v] = v0
        v0 += 1
    mask = np.zeros((2 * hp + 1, 2 * hp + 1), dtype=np.float64)
    for v in range(-hp, hp + 1):
        u = umax[abs(v)]
        mask[v + hp, hp - u : hp + u + 1] = 1.0
    uu, vv = np.meshgrid(np.arange(-hp, hp + 1), np.arange(-hp, hp + 1))
    return mask, uu * mask, vv * mask


_MASK, _U_MASKED, _V_MASKED = _orb_circle_mask()


def ic_angles_deg(gray: np.ndarray, xy_px: np.ndarray) -> np.ndarray:
    """ORB's intensity-centroid orientation (degrees in [0, 360)) at level-0 keypoints."""
    hp = ORB_HALF_PATCH
    if len(xy_px) == 0:
        return np.zeros(0)
    centre = np.round(np.asarray(xy_px, dtype=np.float64)).astype(np.int64)
    padded = np.pad(gray, hp).astype(np.float32)
    offs = np.arange(-hp, hp + 1)
    rows = centre[:, 1, None, None] + offs[None, :, None] + hp
    cols = centre[:, 0, None, None] + offs[None, None, :] + hp
    rows = np.clip(rows, 0, padded.shape[0] - 1)
    cols = np.clip(cols, 0, padded.shape[1] - 1)
    patch = padded[rows, cols]
    m10 = np.einsum("nij,ij->n", patch, _U_MASKED)
    m01 = np.einsum("nij,ij->n", patch, _V_MASKED)
    angle = np.degrees(np.arctan2(m01, m10))
    return np.where(angle < 0, angle + 360.0, angle)


def orb_at_pixels(
    gray: np.ndarray, xy_px: np.ndarray, orb: cv2.ORB | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """ORB descriptors at given raw pixels (level 0, ORB orientation).

    Returns (indices into ``xy_px`` that got a descriptor, (K, 32) uint8 descriptors): points
    too close to the border get none.
    """
    if len(xy_px) == 0:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    angles = ic_angles_deg(gray, xy_px)
    kps = [
        cv2.KeyPoint(float(x), float(y), 31.0, float(a), 0.0, 0, i)
        for i, ((x, y), a) in enumerate(zip(np.asarray(xy_px, dtype=float), angles, strict=True))
    ]
    orb = orb or cv2.ORB_create()
    kept, desc = orb.compute(gray, kps)
    if desc is None or not kept:
        return np.zeros(0, np.int64), np.zeros((0, 32), np.uint8)
    idx = np.array([k.class_id for k in kept], dtype=np.int64)
    return idx, np.ascontiguousarray(desc, dtype=np.uint8)


def undistorted_to_raw_px(intr: CameraIntrinsics, px_undist: np.ndarray) -> np.ndarray:
    """Undistorted pixels of ``K`` -> raw (distorted) image pixels."""
    rays = np.column_stack(
        [
            (px_undist[:, 0] - intr.cx) / intr.fx,
            (px_undist[:, 1] - intr.cy) / intr.fy,
            np.ones(len(px_undist)),
        ]
    )
    return intr.project(rays)


def raw_to_undistorted_px(intr: CameraIntrinsics, px_raw: np.ndarray) -> np.ndarray:
    """Raw image pixels -> undistorted pixels of ``K``."""
    if len(px_raw) == 0:
        return np.zeros((0, 2))
    norm = intr.undistort_points(px_raw)
    return norm * [intr.fx, intr.fy] + [intr.cx, intr.cy]


@dataclass(frozen=True, eq=False)
class KeyframeDescription:
    """Place-recognition data of one keyframe (immutable once built).

    ``query_xy_undist`` (N, 2) / ``query_desc`` (N, 32): ORB keypoints of the whole image;
    ``bow`` their BoW vector. ``landmark_desc`` (M, 32) / ``landmark_points_cam`` (M, 3): ORB
    descriptors at the keyframe's landmark observations and those landmarks in cam0 (metres);
    ``landmark_ids`` (M,) their ids (covisibility); ``landmark_xy_undist`` (M, 2) the front
    end's (undistorted, sub-pixel) observations of them in this keyframe.
    """

    kf_id: int
    t_ns: int
    segment_id: int
    bow: BowVector
    query_xy_undist: np.ndarray
    query_desc: np.ndarray
    landmark_desc: np.ndarray
    landmark_points_cam: np.ndarray
    landmark_ids: np.ndarray
    landmark_xy_undist: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))


@dataclass(frozen=True, eq=False)
class ImageQuery:
    """ORB + BoW of a query image (relocalisation or loop query)."""

    bow: BowVector
    xy_undist: np.ndarray
    desc: np.ndarray


def describe_image(
    gray: np.ndarray, vocab: Vocabulary, intr: CameraIntrinsics, max_features: int
) -> ImageQuery:
    """ORB features of a whole image, their BoW vector and undistorted keypoint pixels."""
    feats: OrbFeatures = detect_orb(gray, max_features=max_features)
    return ImageQuery(
        bow=vocab.transform(feats.descriptors),
        xy_undist=raw_to_undistorted_px(intr, feats.xy_px),
        desc=feats.descriptors,
    )


def describe_keyframe(
    kf: Keyframe,
    world_from_body_vo: np.ndarray,
    body_from_cam0: np.ndarray,
    vocab: Vocabulary,
    intr: CameraIntrinsics,
    max_features: int = 600,
    orb: cv2.ORB | None = None,
) -> KeyframeDescription:
    """Build a keyframe's :class:`KeyframeDescription` (``world_from_body_vo``: the pose the
    keyframe's ``points_world_vo`` were expressed with, normally ``kf.world_from_body_vo``)."""
    image = describe_image(kf.image_left, vocab, intr, max_features)
    px_raw = (
        undistorted_to_raw_px(intr, kf.pixels_left_undist)
        if len(kf.pixels_left_undist)
        else np.zeros((0, 2))
    )
    inside = (
        (px_raw[:, 0] >= 0)
        & (px_raw[:, 1] >= 0)
        & (px_raw[:, 0] < intr.width)
        & (px_raw[:, 1] < intr.height)
    )
    rows = np.flatnonzero(inside)
    idx, desc = orb_at_pixels(kf.image_left, px_raw[rows], orb)
    rows = rows[idx]
    cam_from_world = invert_transform(world_from_body_vo @ body_from_cam0)
    pts_world = np.asarray(kf.points_world_vo, dtype=np.float64)[rows]
    pts_cam = pts_world @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    return KeyframeDescription(
        kf_id=int(kf.keyframe_id),
        t_ns=int(kf.t_ns),
        segment_id=int(kf.segment_id),
        bow=image.bow,
        query_xy_undist=image.xy_undist,
        query_desc=image.desc,
        landmark_desc=desc,
        landmark_points_cam=pts_cam,
        landmark_ids=np.asarray(kf.landmark_ids, dtype=np.int64)[rows],
        landmark_xy_undist=np.asarray(kf.pixels_left_undist, dtype=np.float64)[rows],
    )


class KeyframeStore:
    """Keyframe descriptions, their BoW database and their latest poses, behind one lock.

    The loop closer writes (one thread); the relocaliser reads from the front end's thread.
    Poses: ``odometry`` (world_from_body in the keyframe's segment frame, best known) and
    ``corrected`` (map_from_body after the latest loop correction).
    """

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.database = KeyframeDatabase()
        self._descriptions: dict[int, KeyframeDescription] = {}
        self._odometry: dict[int, np.ndarray] = {}
        self._corrected: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        with self.lock:
            return len(self._descriptions)

    def add_description(self, desc: KeyframeDescription, world_from_body_odom: np.ndarray) -> None:
        """Record a keyframe (the database add is done by the loop detector, under the lock)."""
        with self.lock:
            self._descriptions[desc.kf_id] = desc
            self._odometry[desc.kf_id] = np.array(world_from_body_odom, dtype=float)
            self._corrected.setdefault(desc.kf_id, np.array(world_from_body_odom, dtype=float))

    def description(self, kf_id: int) -> KeyframeDescription:
        with self.lock:
            return self._descriptions[kf_id]

    def has(self, kf_id: int) -> bool:
        with self.lock:
            return kf_id in self._descriptions

    def set_odometry(self, kf_id: int, world_from_body: np.ndarray) -> None:
        with self.lock:
            self._odometry[kf_id] = np.array(world_from_body, dtype=float)

    def odometry(self, kf_id: int) -> np.ndarray:
        with self.lock:
            return self._odometry[kf_id]

    def set_corrected(self, poses: dict[int, np.ndarray]) -> None:
        with self.lock:
            for k, pose in poses.items():
                self._corrected[k] = np.array(pose, dtype=float)

    def corrected(self, kf_id: int) -> np.ndarray:
        with self.lock:
            return self._corrected[kf_id]
