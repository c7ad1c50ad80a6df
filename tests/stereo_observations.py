"""Noisy stereo observations of known points from a known keyframe pose: the synthetic global
adjustment problems of ``test_global_ba.py`` and ``test_global_ba_imu.py``."""

from __future__ import annotations

import numpy as np

from slam.core.geometry import invert_transform


def observe(
    world_from_body: np.ndarray,
    cams: list,
    pts_world: np.ndarray,
    pixel_sigma_px: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The points seen by every camera of the rig (in front of it by 0.5 m, inside its
    image): their indices, the left and right pixels with ``pixel_sigma_px`` noise, and their
    cam0 coordinates with 1 cm noise (the front end's stereo depth)."""
    uvs, ok = [], np.ones(len(pts_world), bool)
    for cam in cams:
        pc = invert_transform(world_from_body @ cam.body_from_cam)
        x = pts_world @ pc[:3, :3].T + pc[:3, 3]
        z = np.maximum(x[:, 2:3], 1e-9)
        u = (x / z) @ cam.intrinsics.K.T
        ok &= (x[:, 2] > 0.5) & (u[:, 0] >= 0) & (u[:, 1] >= 0)
        ok &= (u[:, 0] < cam.intrinsics.width) & (u[:, 1] < cam.intrinsics.height)
        uvs.append(u[:, :2] + rng.normal(0, pixel_sigma_px, (len(pts_world), 2)))
    j = np.flatnonzero(ok)
    c0 = invert_transform(world_from_body @ cams[0].body_from_cam)
    p_cam0 = pts_world[j] @ c0[:3, :3].T + c0[:3, 3] + rng.normal(0, 0.01, (len(j), 3))
    return j, uvs[0][j], uvs[1][j], p_cam0
