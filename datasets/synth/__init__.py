"""Synthetic stereo-inertial sequences with exact ground truth.

``scene`` (textured room + boxes), ``render`` (vectorised ray casting), ``trajectories``
(analytic motion profiles and spline-fitted trajectory files), ``imu_sim`` (IMU from the
analytic derivatives + noise), ``generator`` (the lazy :class:`SyntheticSequence`; its rig is
``datasets.rigs.euroc_like_calibration``).
"""

from datasets.synth.generator import SyntheticSequence, make_synthetic_sequence

__all__ = ["SyntheticSequence", "make_synthetic_sequence"]
