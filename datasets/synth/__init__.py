"""Synthetic stereo-inertial sequences with exact ground truth.

``scene`` (textured room + boxes), ``render`` (vectorised ray casting), ``trajectories``
(analytic motion profiles and spline-fitted trajectory files), ``imu_sim`` (IMU from the
analytic derivatives + noise), ``generator`` (the lazy :class:`SyntheticSequence`).
"""

from datasets.synth.generator import (
    SyntheticSequence,
    euroc_like_calibration,
    make_synthetic_sequence,
)

__all__ = ["SyntheticSequence", "euroc_like_calibration", "make_synthetic_sequence"]
