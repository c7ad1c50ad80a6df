"""The camera rigs built in code (readers take theirs from the data): two different rigs.

- :func:`euroc_like_calibration`: EuRoC MAV's VI-Sensor as in the dataset's sensor.yaml files:
  752x480, each camera's own intrinsics and radtan distortion, the dataset's body_from_cam
  (T_BS; 0.110 m baseline, cameras along body +z), 20 Hz; IMU at 200 Hz with the ADIS16448
  noise figures. The synthetic generator renders with it; ``distortion=False`` is the same rig
  with ideal pinhole lenses (the back-end simulation, which renders no images, projects with
  it).
- :func:`small_rig_calibration`: an idealised stereo rig for small in-memory test images: any
  image size, both cameras with EuRoC cam0's focal lengths and distortion and the principal
  point near the image centre, exactly 0.110 m apart along body y, looking along body +x with
  no mounting error.
"""

from __future__ import annotations

import numpy as np

from slam.core.calibration import Calibration, CameraCalibration, CameraIntrinsics, ImuCalibration
from slam.core.geometry import make_transform

FRAME_RATE_HZ = 20.0
IMU_RATE_HZ = 200.0

# EuRoC MAV cam0/cam1 (VI-Sensor, MT9M034) as in the dataset's sensor.yaml files
_EUROC_FX_FY_CX_CY = ((458.654, 457.296, 367.215, 248.375), (457.587, 456.134, 379.999, 255.238))
_EUROC_RADTAN = (
    (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05),
    (-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05),
)
_EUROC_BODY_FROM_CAM = (
    np.array(
        [
            [0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
            [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
            [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949],
            [0.0, 0.0, 0.0, 1.0],
        ]
    ),
    np.array(
        [
            [0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556],
            [0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024],
            [-0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038],
            [0.0, 0.0, 0.0, 1.0],
        ]
    ),
)


def euroc_like_calibration(
    imu: ImuCalibration | None = None, *, distortion: bool = True
) -> Calibration:
    """Stereo 752x480 at 20 Hz with EuRoC's intrinsics, radtan distortion (none with
    ``distortion=False``) and extrinsics (baseline 0.110 m), IMU at 200 Hz with the ADIS16448
    noise figures."""
    cams = []
    for i in range(2):
        lens = ("radtan", _EUROC_RADTAN[i]) if distortion else ()
        intr = CameraIntrinsics(752, 480, *_EUROC_FX_FY_CX_CY[i], *lens)
        cams.append(
            CameraCalibration(f"cam{i}", intr, _EUROC_BODY_FROM_CAM[i].copy(), FRAME_RATE_HZ)
        )
    return Calibration(
        cameras=tuple(cams), imu=imu or ImuCalibration(rate_hz=IMU_RATE_HZ), time_offset_ns=0
    )


def small_rig_calibration(
    width: int = 752, height: int = 480, stereo: bool = True, time_offset_ns: int = 0
) -> Calibration:
    """A stereo rig for small in-memory test images: EuRoC cam0's focal lengths and radtan
    distortion at any image size, 11 cm baseline, cameras looking along body +x."""
    fx, fy = _EUROC_FX_FY_CX_CY[0][:2]
    intr = CameraIntrinsics(
        width, height, fx, fy, width / 2 - 8.8, height / 2 + 8.4, "radtan", _EUROC_RADTAN[0]
    )
    cam_rot = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # z_cam = x_body
    cams = [CameraCalibration("cam0", intr, make_transform(cam_rot, np.array([0.0, 0.055, 0.0])))]
    if stereo:
        cams.append(
            CameraCalibration("cam1", intr, make_transform(cam_rot, np.array([0.0, -0.055, 0.0])))
        )
    return Calibration(tuple(cams), ImuCalibration(), time_offset_ns=time_offset_ns)
