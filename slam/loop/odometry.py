"""Which keyframes' odometry poses the loop closer must be told again, and which keyframes stay
out of the global adjustment."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam.core.geometry import invert_transform, is_rigid, rotation_angle_rad

REFRESH_LAST_KEYFRAMES = 30  # odometry poses re-read per new keyframe (the back end's window)
FULL_REFRESH_EVERY = 10  # ... and the older ones', every this many keyframes (see below)
FRAME_JUMP_M = 0.1  # an old keyframe moving more than this between sweeps: a change of frame
FRAME_JUMP_DEG = 3.0
RIGID_TOL = 1e-6  # max |R^T R - I| of an odometry pose the closer accepts


class OdometryRefresher:
    """Which keyframes' odometry poses changed since they were last handed to the closer.

    Every keyframe, the last ``REFRESH_LAST_KEYFRAMES`` are re-read (the back end's window keeps
    refining them). Every ``FULL_REFRESH_EVERY`` keyframes, the older ones are re-read too, but
    resent only when they *jumped* since the previous sweep by more than a change of frame
    threshold (``FRAME_JUMP_M`` / ``FRAME_JUMP_DEG``). Why both rules, measured:

    * at ``--speed max`` on the hall, the back end's first (gravity-aligning) estimate arrived
      ~40 keyframes late, after the first 10 keyframes had left the recent window: they stayed
      in the pre-initialisation VO frame (a 94 deg wrong odometry edge; loops to the start
      rejected by the robust kernel). The sweep catches such a change of frame;
    * keyframes without a back-end pose (before initialisation) come from the front end's
      belief, which every estimate re-anchors by the current drift correction: resending all
      their small changes dragged keyframe 1 of room-aggressive 115 mm / 2.2 deg away from
      keyframe 2 (corrupting every loop to it). Small changes of old keyframes are ignored.
    """

    def __init__(self, odometry_pose: Callable[[int], np.ndarray | None]):
        self._source = odometry_pose
        self.sent: dict[int, np.ndarray] = {}
        self._seen: dict[int, np.ndarray] = {}  # old keyframes' source poses at the last sweep
        self._order: list[int] = []
        self.invalid_poses = 0
        self.frame_jumps = 0

    def odometry_pose(self, kid: int) -> np.ndarray | None:
        """The source's pose when it is a rigid transform, else None (counted): measured, a
        diverging back end once published a keyframe pose with a 'rotation' of norm ~12."""
        pose = self._source(kid)
        if pose is None:
            return None
        pose = np.asarray(pose, dtype=float)
        if not is_rigid(pose, tol=RIGID_TOL):
            self.invalid_poses += 1
            return None
        return pose

    def refreshed(self, full: bool = False) -> dict[int, np.ndarray]:
        """Changed poses to resend before the next keyframe (also recorded as sent); ``full``:
        sweep the old keyframes now (at the end of the run)."""
        out: dict[int, np.ndarray] = {}
        recent = self._order[-REFRESH_LAST_KEYFRAMES:]
        for kid in recent:
            pose = self.odometry_pose(kid)
            if pose is None:
                continue
            self._seen[kid] = pose
            old = self.sent.get(kid)
            if old is None or not np.array_equal(old, pose):
                out[kid] = self.sent[kid] = np.array(pose, dtype=float)
        if full or len(self._order) % FULL_REFRESH_EVERY == 0:
            # Vectorised over the old keyframes: this runs in the main process, and a Python
            # loop over hundreds of poses held the GIL for milliseconds at a time.
            old_ids = self._order[: max(len(self._order) - len(recent), 0)]
            found = [(kid, p) for kid in old_ids if (p := self._source(kid)) is not None]
            if not found:
                return out
            ids = [kid for kid, _ in found]
            poses = np.array([p for _, p in found], dtype=float).reshape(-1, 4, 4)
            before_all = np.array([self._seen.get(k, self.sent[k]) for k in ids]).reshape(-1, 4, 4)
            valid = is_rigid(poses, tol=RIGID_TOL)
            self.invalid_poses += int((~valid).sum())
            changed = valid & ~(poses == before_all).all(axis=(1, 2))  # usually: frozen poses
            for i in np.flatnonzero(changed).tolist():
                kid, pose, before = ids[i], poses[i], before_all[i]
                self._seen[kid] = pose.copy()
                jump = invert_transform(before) @ pose
                angle_deg = float(np.degrees(rotation_angle_rad(jump[:3, :3])))
                if np.linalg.norm(jump[:3, 3]) > FRAME_JUMP_M or angle_deg > FRAME_JUMP_DEG:
                    out[kid] = self.sent[kid] = np.array(pose, dtype=float)
                    self.frame_jumps += 1
        return out

    def new_keyframe(self, kid: int, fallback: np.ndarray) -> np.ndarray:
        """The odometry pose to send with a new keyframe (``fallback`` when none is known)."""
        pose = self.odometry_pose(kid)
        odom = np.array(fallback if pose is None else pose, dtype=float)
        self.sent[kid] = odom
        self._order.append(kid)
        return odom


def before_first_smoothed(kf_ids: list[int], smoothed: Callable[[int], bool]) -> set[int]:
    """The keyframes before the first one the back end estimated (its initialisation). Only
    those: at the end of a run, the back end may still be busy with the newest keyframes."""
    first = min((k for k in kf_ids if smoothed(k)), default=None)
    return set() if first is None else {k for k in kf_ids if k < first}
