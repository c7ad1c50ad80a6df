"""Our MCAP files: write -> read round trip, and independent readers (rosbags, mcap-ros2)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from datasets import cdr
from datasets.mcap_io import McapSequence, write_sequence_mcap
from datasets.memory import random_sequence
from slam.core.messages import ImuSample, StereoFrame


@pytest.fixture(scope="module")
def written(tmp_path_factory: pytest.TempPathFactory):
    seq = random_sequence(num_frames=24, width=160, height=120, time_offset_ns=-1_234_567, seed=3)
    path = tmp_path_factory.mktemp("mcap") / "seq.mcap"
    write_sequence_mcap(seq, path, progress=False)
    return seq, path


def test_round_trip_bit_identical(written) -> None:
    seq, path = written
    back = McapSequence(path)
    assert back.warnings == []
    assert back.name == seq.name
    assert back.num_frames == seq.num_frames == 24
    np.testing.assert_array_equal(back.frame_times_ns(), seq.frame_times_ns())
    for a, b in zip(back.iter_frames(), seq.iter_frames(), strict=True):
        assert a.t_ns == b.t_ns
        assert a.left.dtype == np.uint8 and np.array_equal(a.left, b.left)
        assert b.right is not None and a.right is not None and np.array_equal(a.right, b.right)
    for i in (0, 13, 23, 5):  # random access, out of order
        assert np.array_equal(back.frame(i).left, seq.frame(i).left)
    imu_a, imu_b = back.imu(), seq.imu()
    np.testing.assert_array_equal(imu_a.t_ns, imu_b.t_ns)
    np.testing.assert_array_equal(imu_a.gyro_rad_s, imu_b.gyro_rad_s)
    np.testing.assert_array_equal(imu_a.accel_m_s2, imu_b.accel_m_s2)
    assert back.ground_truth is not None and seq.ground_truth is not None
    np.testing.assert_array_equal(back.ground_truth.t_ns, seq.ground_truth.t_ns)
    np.testing.assert_array_equal(back.ground_truth.positions_m, seq.ground_truth.positions_m)
    np.testing.assert_array_equal(back.ground_truth.q_wxyz, seq.ground_truth.q_wxyz)
    assert back.calibration.to_dict() == seq.calibration.to_dict()
    # merged stream: every message, in time order
    msgs = list(back.messages())
    assert sum(isinstance(m, StereoFrame) for m in msgs) == 24
    assert sum(isinstance(m, ImuSample) for m in msgs) == len(imu_b)
    assert all(a.t_ns <= b.t_ns for a, b in zip(msgs, msgs[1:]))


def test_ros2_metadata_and_rosbags_reader(written) -> None:
    """rosbags (an independent reader) opens the file and decodes every message."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    seq, path = written
    with open(path, "rb") as fh:
        from mcap.reader import make_reader

        reader = make_reader(fh)
        header = reader.get_header()
        summary = reader.get_summary()
        assert summary is not None
        assert header.profile == "ros2"
        assert {c.message_encoding for c in summary.channels.values()} == {"cdr"}
        assert {s.encoding for s in summary.schemas.values()} == {"ros2msg"}
        assert {c.compression for c in summary.chunk_indexes} == {"zstd"}
        meta = {m.name for m in reader.iter_metadata()}
        assert {"pyvislam.calibration", "pyvislam.sequence"} <= meta

    ts = get_typestore(Stores.ROS2_HUMBLE)
    with AnyReader([Path(path)], default_typestore=ts) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        assert types == {
            "/cam0/image_raw": "sensor_msgs/msg/Image",
            "/cam1/image_raw": "sensor_msgs/msg/Image",
            "/cam0/camera_info": "sensor_msgs/msg/CameraInfo",
            "/cam1/camera_info": "sensor_msgs/msg/CameraInfo",
            "/imu0": "sensor_msgs/msg/Imu",
            "/groundtruth/pose": "geometry_msgs/msg/PoseStamped",
        }
        offset = seq.calibration.time_offset_ns
        lefts = []
        for con, _t, raw in r.messages(
            connections=[c for c in r.connections if c.topic == "/cam0/image_raw"]
        ):
            msg = r.deserialize(raw, con.msgtype)
            stamp = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
            lefts.append((stamp + offset, msg.data.reshape(msg.height, msg.width)))
        assert len(lefts) == seq.num_frames
        for (t_ns, img), frame in zip(lefts, seq.iter_frames(), strict=True):
            assert t_ns == frame.t_ns and np.array_equal(img, frame.left)
        infos = [
            r.deserialize(raw, con.msgtype)
            for con, _t, raw in r.messages(
                connections=[c for c in r.connections if c.topic == "/cam0/camera_info"]
            )
        ]
        k = seq.calibration.cam0.intrinsics.K
        np.testing.assert_allclose(infos[0].k.reshape(3, 3), k)
        assert infos[0].distortion_model == "plumb_bob"


def test_mcap_ros2_decoder_reads_imu(written) -> None:
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    seq, path = written
    gyro = []
    with open(path, "rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        for _s, _c, _m, msg in reader.iter_decoded_messages(topics=["/imu0"]):
            v = msg.angular_velocity
            gyro.append((v.x, v.y, v.z))
    np.testing.assert_array_equal(np.array(gyro), seq.imu().gyro_rad_s)


def test_cdr_encoders_match_rosbags_serializer() -> None:
    """Our hand-written CDR bytes equal rosbags' serializer output for the same message."""
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    rng = np.random.default_rng(0)
    img = rng.integers(0, 256, (7, 9), dtype=np.uint8)
    for data, msgtype in [
        (cdr.encode_image_mono8(1_000_000_123, "cam0", img), "sensor_msgs/msg/Image"),
        (cdr.encode_imu(5, "imu", rng.normal(size=3), rng.normal(size=3)), "sensor_msgs/msg/Imu"),
        (
            cdr.encode_pose_stamped(9, "w", rng.normal(size=3), np.array([1.0, 0, 0, 0])),
            "geometry_msgs/msg/PoseStamped",
        ),
        (
            cdr.encode_camera_info(3, "c", 752, 480, "plumb_bob", [0.1, 0.2, 0, 0, 0], np.eye(3)),
            "sensor_msgs/msg/CameraInfo",
        ),
    ]:
        msg = ts.deserialize_cdr(data, msgtype)
        assert bytes(ts.serialize_cdr(msg, msgtype)) == data, msgtype


def test_mono_sequence_round_trip(tmp_path: Path) -> None:
    seq = random_sequence(num_frames=5, stereo=False, seed=1)
    path = tmp_path / "mono.mcap"
    write_sequence_mcap(seq, path, progress=False)
    back = McapSequence(path)
    assert not back.calibration.is_stereo
    frames = list(back.iter_frames())
    assert len(frames) == 5 and all(f.right is None for f in frames)
    assert np.array_equal(frames[2].left, seq.frame(2).left)


def test_atomic_write_leaves_no_partial_file(tmp_path: Path) -> None:
    class Boom(Exception):
        pass

    seq = random_sequence(num_frames=5, seed=2)
    original = seq.frame

    def failing(i: int):  # type: ignore[no-untyped-def]
        if i == 3:
            raise Boom
        return original(i)

    seq.frame = failing  # type: ignore[method-assign]
    with pytest.raises(Boom):
        write_sequence_mcap(seq, tmp_path / "x.mcap", progress=False)
    assert list(tmp_path.iterdir()) == []


def test_vectorised_imu_decode_matches_single() -> None:
    rng = np.random.default_rng(4)
    payloads = [
        cdr.encode_imu(
            int(rng.integers(0, 2 * 10**18)), fid, rng.normal(size=3), rng.normal(size=3)
        )
        for fid in ("imu0", "imu", "a_longer_frame_id", "imu0", "", "imu")
    ]
    t, gyro, accel = cdr.decode_imu_many(payloads)
    for k, p in enumerate(payloads):
        t1, g1, a1 = cdr.decode_imu(p)
        assert t[k] == t1 and tuple(gyro[k]) == g1 and tuple(accel[k]) == a1


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_other_chunk_compressions(tmp_path: Path, compression: str) -> None:
    seq = random_sequence(num_frames=6, seed=6)
    path = tmp_path / f"{compression}.mcap"
    write_sequence_mcap(seq, path, progress=False, compression=compression)
    back = McapSequence(path)
    assert back.warnings == []
    for a, b in zip(back.iter_frames(), seq.iter_frames(), strict=True):
        assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)
    np.testing.assert_array_equal(back.imu().accel_m_s2, seq.imu().accel_m_s2)


def _resident_kb_of(path: Path) -> int:
    """Resident kB of this process's mappings of ``path`` (``/proc/self/smaps``)."""
    total, inside = 0, False
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if head and "-" in head[0] and not head[0].endswith(":"):  # a mapping's first line
            inside = line.endswith(str(path))
        elif inside and line.startswith("Rss:"):
            total += int(head[1])
    return total


@pytest.mark.skipif(not Path("/proc/self/smaps").exists(), reason="needs Linux /proc")
def test_reading_a_recording_does_not_keep_its_file_pages(tmp_path: Path) -> None:
    """Frames read leave their pages of the recording out of the process's resident memory
    (they stayed: a reader process grew as large as the file it read)."""
    seq = random_sequence(num_frames=60, width=640, height=480, seed=5)  # noise: no compression
    path = tmp_path / "big.mcap"
    write_sequence_mcap(seq, path, progress=False, compression="none")
    size_kb = path.stat().st_size // 1024
    assert size_kb > 30_000
    frames = McapSequence(path).iter_frames()
    for _ in range(45):  # three quarters of the file read; still mapped
        next(frames)
    resident_kb = _resident_kb_of(path)
    frames.close()
    assert resident_kb < 0.05 * size_kb, (resident_kb, size_kb)
