"""Plain ROS 2 bags (MCAP) recorded by someone else: topics by option, Kalibr calibration,
colour and compressed images; and the real nav2 MCAP from evo's test data."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from conftest import require

from datasets.info import describe
from datasets.kalibr import load_kalibr
from datasets.mcap_scan import scan_mcap
from datasets.open import open_sequence
from slam.core.errors import InputError
from slam.core.geometry import invert_transform

CAM_FROM_IMU_0 = [
    [0.0148655429818, 0.999557249008, -0.0257744366974, 0.0652229095355],
    [-0.999880929698, 0.0149672133247, 0.00375618835797, -0.0207006278303],
    [0.00414029679422, 0.025715529948, 0.999660727178, -0.0080546004471],
    [0.0, 0.0, 0.0, 1.0],
]
CAM_FROM_IMU_1 = [
    [0.0125552670891, 0.999598781151, -0.0253898008918, -0.0444287005285],
    [-0.999755099723, 0.0130119051815, 0.0179005838253, -0.0211796152839],
    [0.0182237714554, 0.0251588363115, 0.999517347078, -0.0082611215496],
    [0.0, 0.0, 0.0, 1.0],
]


def write_kalibr(tmp: Path, model: str = "radtan") -> tuple[Path, Path]:
    import yaml

    coeffs = [-0.28, 0.07, 0.0002, 1.7e-5] if model == "radtan" else [0.01, -0.002, 0.001, -0.0003]
    chain = {
        f"cam{i}": {
            "T_cam_imu": m,
            "camera_model": "pinhole",
            "distortion_coeffs": coeffs,
            "distortion_model": model,
            "intrinsics": [458.654, 457.296, 367.215, 248.375],
            "resolution": [64, 48],
            "rostopic": f"/stereo/{side}/image",
            "timeshift_cam_imu": 0.0025,
        }
        for i, (m, side) in enumerate(((CAM_FROM_IMU_0, "left"), (CAM_FROM_IMU_1, "right")))
    }
    imu = {
        "imu0": {
            "accelerometer_noise_density": 0.0028,
            "accelerometer_random_walk": 0.00086,
            "gyroscope_noise_density": 0.00016,
            "gyroscope_random_walk": 2.2e-05,
            "rostopic": "/sensors/imu",
            "update_rate": 400.0,
        }
    }
    (tmp / "camchain.yaml").write_text(yaml.safe_dump(chain))
    (tmp / "imu.yaml").write_text(yaml.safe_dump(imu))
    return tmp / "camchain.yaml", tmp / "imu.yaml"


def write_foreign_bag(tmp: Path, n_frames: int = 6, compressed_right: bool = True):
    """A rosbags-written bag: bgr8 left, jpeg/png right, IMU at 400 Hz, Odometry ground truth."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    Image = ts.types["sensor_msgs/msg/Image"]
    CompressedImage = ts.types["sensor_msgs/msg/CompressedImage"]
    Imu = ts.types["sensor_msgs/msg/Imu"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    Vector3 = ts.types["geometry_msgs/msg/Vector3"]
    Quaternion = ts.types["geometry_msgs/msg/Quaternion"]

    rng = np.random.default_rng(7)
    t0 = 1_600_000_000_000_000_000
    bag = tmp / "foreign_bag"
    lefts, rights, imu_rows = [], [], []
    with Writer(bag, version=8, storage_plugin=StoragePlugin.MCAP) as w:
        c_left = w.add_connection("/stereo/left/image", "sensor_msgs/msg/Image", typestore=ts)
        rtype = "sensor_msgs/msg/CompressedImage" if compressed_right else "sensor_msgs/msg/Image"
        c_right = w.add_connection("/stereo/right/image", rtype, typestore=ts)
        c_imu = w.add_connection("/sensors/imu", "sensor_msgs/msg/Imu", typestore=ts)

        def header(t: int, fid: str):  # type: ignore[no-untyped-def]
            return Header(stamp=Time(sec=t // 10**9, nanosec=t % 10**9), frame_id=fid)

        for k in range(n_frames * 20):
            t = t0 + k * 2_500_000
            g, a = rng.normal(size=3), rng.normal(size=3)
            imu_rows.append((t, g, a))
            msg = Imu(
                header=header(t, "imu"),
                orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                orientation_covariance=np.zeros(9),
                angular_velocity=Vector3(x=g[0], y=g[1], z=g[2]),
                angular_velocity_covariance=np.zeros(9),
                linear_acceleration=Vector3(x=a[0], y=a[1], z=a[2]),
                linear_acceleration_covariance=np.zeros(9),
            )
            w.write(c_imu, t, ts.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
            if k % 20:
                continue
            bgr = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
            lefts.append((t, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)))
            img = Image(
                header=header(t, "left"), height=48, width=64, encoding="bgr8",
                is_bigendian=0, step=64 * 3, data=bgr.reshape(-1),
            )  # fmt: skip
            w.write(c_left, t, ts.serialize_cdr(img, "sensor_msgs/msg/Image"))
            grey = rng.integers(0, 256, (48, 64), dtype=np.uint8)
            rights.append((t, grey))
            if compressed_right:
                ok, png = cv2.imencode(".png", grey)
                assert ok
                cimg = CompressedImage(
                    header=header(t, "right"), format="png", data=png.reshape(-1)
                )
                w.write(c_right, t, ts.serialize_cdr(cimg, rtype))
            else:
                img = Image(
                    header=header(t, "right"), height=48, width=64, encoding="mono16",
                    is_bigendian=0, step=128, data=np.zeros(48 * 128, np.uint8),
                )  # fmt: skip
                w.write(c_right, t, ts.serialize_cdr(img, rtype))
    return bag, lefts, rights, imu_rows


def test_kalibr_parsing(tmp_path: Path) -> None:
    camchain, imu_yaml = write_kalibr(tmp_path, "equidistant")
    kal = load_kalibr(camchain, imu_yaml)
    cal = kal.calibration
    assert kal.camera_topics == ("/stereo/left/image", "/stereo/right/image")
    assert kal.imu_topic == "/sensors/imu"
    assert cal.time_offset_ns == 2_500_000
    assert cal.cam0.intrinsics.distortion_model == "equidistant"
    np.testing.assert_allclose(cal.cam0.body_from_cam, invert_transform(np.array(CAM_FROM_IMU_0)))
    np.testing.assert_allclose(
        cal.cam0.body_from_cam @ np.array(CAM_FROM_IMU_0), np.eye(4), atol=1e-12
    )
    assert cal.imu is not None and cal.imu.rate_hz == 400.0
    assert cal.imu.accel_noise_density == 0.0028 and cal.imu.gyro_random_walk == 2.2e-05
    # the EuRoC stereo baseline (11 cm) comes out of the two T_cam_imu
    assert abs(cal.stereo_baseline_m() - 0.110) < 0.001


def test_foreign_bag_with_kalibr(tmp_path: Path) -> None:
    bag, lefts, rights, imu_rows = write_foreign_bag(tmp_path)
    camchain, imu_yaml = write_kalibr(tmp_path)
    # topics come from the Kalibr files' rostopic entries
    seq = open_sequence(bag, camchain=camchain, imu_yaml=imu_yaml)
    assert seq.num_frames == len(lefts) == 6
    offset = seq.calibration.time_offset_ns
    assert offset == 2_500_000
    for frame, (t, grey_l), (_, grey_r) in zip(seq.iter_frames(), lefts, rights, strict=True):
        assert frame.t_ns == t + offset  # camera stamps moved to the IMU clock
        assert np.array_equal(frame.left, grey_l)  # bgr8 -> grey as OpenCV does it
        assert frame.right is not None and np.array_equal(frame.right, grey_r)  # png
    imu = seq.imu()
    np.testing.assert_array_equal(imu.t_ns, [r[0] for r in imu_rows])
    np.testing.assert_array_equal(imu.gyro_rad_s, np.array([r[1] for r in imu_rows]))
    np.testing.assert_array_equal(imu.accel_m_s2, np.array([r[2] for r in imu_rows]))
    assert seq.ground_truth is None


def test_foreign_bag_without_calibration_says_how(tmp_path: Path) -> None:
    bag, *_ = write_foreign_bag(tmp_path)
    with pytest.raises(InputError, match="--camchain"):
        open_sequence(bag, left_topic="/stereo/left/image", right_topic="/stereo/right/image")


def test_unknown_encoding_lists_topics(tmp_path: Path) -> None:
    bag, *_ = write_foreign_bag(tmp_path, compressed_right=False)
    camchain, imu_yaml = write_kalibr(tmp_path)
    with pytest.raises(InputError, match="mono16") as err:
        open_sequence(bag, camchain=camchain, imu_yaml=imu_yaml)
    assert "/stereo/left/image" in str(err.value) and "/sensors/imu" in str(err.value)


def test_nav2_turtlebot_mcap(shared_data: Path) -> None:
    """A real ROS 2 recording with odometry/tf only: its topics list, and opening it as a
    sequence fails with the list of topics that are there."""
    path = require(shared_data / "trajectories" / "evo_testdata" / "nav2_turtlebot.mcap")
    scan = scan_mcap(path)
    assert scan.profile == "ros2" and scan.complete and not scan.warnings
    topics = scan.topics()
    assert topics["/odom"][0] == "nav_msgs/msg/Odometry"
    assert topics["/amcl_pose"][0] == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert {"/tf", "/tf_static"} <= set(topics)
    # counts agree with the mcap library's own summary
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    ref = summary.statistics.channel_message_counts
    for cid, ch in summary.channels.items():
        assert topics[ch.topic][1] == ref[cid]
    with pytest.raises(InputError) as err:
        open_sequence(path)
    msg = str(err.value)
    assert "/cam0/image_raw not found" in msg
    for topic in ("/odom", "/tf", "/amcl_pose"):
        assert topic in msg
    lines, usable = describe(path)
    assert not usable and any("/odom" in ln for ln in lines)
