"""RGB-D folders in the Microsoft 7-Scenes layout (as used by tsdf-fusion demos).

Layout: ``frame-XXXXXX.color.jpg|png`` (RGB), ``frame-XXXXXX.depth.png`` (uint16 millimetres,
0 = no depth), ``frame-XXXXXX.pose.txt`` (4x4 world_from_camera), and optionally
``camera-intrinsics.txt`` (3x3 K). The frames may sit in the folder itself or in ``data/``.
Without an intrinsics file the 7-Scenes default (fx = fy = 585, cx = 320, cy = 240) is used.
There are no timestamps; ``t_ns`` is synthesised at ``rate_hz`` (30 Hz for a Kinect).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from slam.core.errors import InputError

SEVEN_SCENES_K = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
_FRAME_RE = re.compile(r"^frame-(\d+)\.depth\.png$")


@dataclass(frozen=True, eq=False)
class RgbdFrame:
    """One RGB-D frame: colour (H, W, 3) uint8 RGB, depth (H, W) float32 metres (0 = invalid)."""

    t_ns: int
    index: int
    color_rgb: np.ndarray
    depth_m: np.ndarray
    world_from_cam: np.ndarray


class RgbdFolder:
    """Random access to the frames of a 7-Scenes-layout folder."""

    def __init__(self, path: str | Path, rate_hz: float = 30.0) -> None:
        root = Path(path)
        if not root.is_dir():
            raise InputError(f"{root}: not a folder; give a 7-Scenes-style RGB-D folder")
        if not any(_FRAME_RE.match(p.name) for p in root.iterdir()) and (root / "data").is_dir():
            root = root / "data"
        ids = sorted(int(m.group(1)) for p in root.iterdir() if (m := _FRAME_RE.match(p.name)))
        if not ids:
            raise InputError(f"{root}: no frame-XXXXXX.depth.png files (7-Scenes layout expected)")
        self.root = root
        self.frame_ids = ids
        self.rate_hz = rate_hz
        k_file = root / "camera-intrinsics.txt"
        self.K = np.loadtxt(k_file).reshape(3, 3) if k_file.exists() else SEVEN_SCENES_K.copy()

    def __len__(self) -> int:
        return len(self.frame_ids)

    def _name(self, i: int, suffix: str) -> Path:
        return self.root / f"frame-{self.frame_ids[i]:06d}.{suffix}"

    def has_poses(self) -> bool:
        return self._name(0, "pose.txt").exists()

    def pose(self, i: int) -> np.ndarray:
        """world_from_cam (4x4) of frame i."""
        path = self._name(i, "pose.txt")
        try:
            pose = np.loadtxt(path).reshape(4, 4)
        except (OSError, ValueError) as exc:
            raise InputError(f"{path}: cannot read a 4x4 pose ({exc})") from exc
        return pose

    def t_ns(self, i: int) -> int:
        return int(round(self.frame_ids[i] * 1e9 / self.rate_hz))

    def depth_m(self, i: int) -> np.ndarray:
        path = self._name(i, "depth.png")
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None:
            raise InputError(f"{path}: cannot read the depth PNG")
        depth = raw.astype(np.float32) * 1e-3  # millimetres -> metres
        depth[raw >= 65535] = 0.0  # some sensors mark invalid as 65535
        return depth

    def color_rgb(self, i: int) -> np.ndarray:
        for suffix in ("color.jpg", "color.png"):
            path = self._name(i, suffix)
            if path.exists():
                bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
                if bgr is None:
                    raise InputError(f"{path}: cannot read the colour image")
                return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)  # OpenCV reads BGR
        raise InputError(f"{self._name(i, 'color.jpg')}: colour image missing")

    def frame(self, i: int) -> RgbdFrame:
        return RgbdFrame(
            t_ns=self.t_ns(i),
            index=self.frame_ids[i],
            color_rgb=self.color_rgb(i),
            depth_m=self.depth_m(i),
            world_from_cam=self.pose(i),
        )
