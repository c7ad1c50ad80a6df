"""Middlebury multi-view stereo data (``*_par.txt`` calibration + PNG images).

Each line of ``NAME_par.txt`` is ``imgname.png k11..k33 r11..r33 t1 t2 t3`` with projection
``K [R | t]``: ``[R | t]`` maps world points into the camera (cam_from_world).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam.core.errors import InputError


@dataclass(frozen=True, eq=False)
class MvsView:
    """One calibrated view: image name, 3x3 K and 4x4 cam_from_world."""

    name: str
    K: np.ndarray
    cam_from_world: np.ndarray

    @property
    def world_from_cam(self) -> np.ndarray:
        return np.linalg.inv(self.cam_from_world)


def read_middlebury_par(path: str | Path) -> dict[str, MvsView]:
    """Parse a ``*_par.txt`` file into views keyed by image name."""
    path = Path(path)
    views: dict[str, MvsView] = {}
    lines = path.read_text().split("\n")
    for lineno, line in enumerate(lines[1:], start=2):  # first line: the number of views
        parts = line.split()
        if not parts:
            continue
        if len(parts) != 22:
            raise InputError(
                f"{path}:{lineno}: expected 22 fields (name, K, R, t), got {len(parts)}"
            )
        vals = np.array([float(x) for x in parts[1:]])
        pose = np.eye(4)
        pose[:3, :3] = vals[9:18].reshape(3, 3)
        pose[:3, 3] = vals[18:21]
        views[parts[0]] = MvsView(parts[0], vals[:9].reshape(3, 3), pose)
    return views


def read_image_rgb(path: str | Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise InputError(f"{path}: cannot read the image")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)  # OpenCV reads BGR
