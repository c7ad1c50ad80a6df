"""ORB features for place recognition and loop verification (OpenCV's ORB, 256-bit BRIEF)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True, eq=False)
class OrbFeatures:
    """Keypoints of one image: ``xy_px`` (N, 2) float32 pixel positions, ``descriptors``
    (N, 32) uint8, ``octaves`` (N,) int32 pyramid level, ``responses`` (N,) float32."""

    xy_px: np.ndarray
    descriptors: np.ndarray
    octaves: np.ndarray
    responses: np.ndarray

    def __len__(self) -> int:
        return len(self.xy_px)


def detect_orb(
    gray: np.ndarray,
    max_features: int = 1000,
    scale_factor: float = 1.2,
    num_levels: int = 8,
    fast_threshold: int = 20,
) -> OrbFeatures:
    """ORB keypoints and descriptors of an 8-bit grey (or BGR) image."""
    if gray.ndim == 3:
        gray = cv2.cvtColor(gray, cv2.COLOR_BGR2GRAY)
    orb = cv2.ORB_create(
        nfeatures=max_features,
        scaleFactor=scale_factor,
        nlevels=num_levels,
        fastThreshold=fast_threshold,
    )
    keypoints, descriptors = orb.detectAndCompute(gray, None)
    if descriptors is None or not keypoints:
        return OrbFeatures(
            np.zeros((0, 2), np.float32),
            np.zeros((0, 32), np.uint8),
            np.zeros(0, np.int32),
            np.zeros(0, np.float32),
        )
    return OrbFeatures(
        xy_px=np.array([kp.pt for kp in keypoints], dtype=np.float32),
        descriptors=np.ascontiguousarray(descriptors, dtype=np.uint8),
        octaves=np.array([kp.octave for kp in keypoints], dtype=np.int32),
        responses=np.array([kp.response for kp in keypoints], dtype=np.float32),
    )
