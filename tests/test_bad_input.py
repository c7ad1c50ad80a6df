"""Bad input is never silent and never a traceback: each case warns or raises InputError."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from mcap.writer import CompressionType, Writer

from datasets import cdr
from datasets.mcap_io import McapSequence, ros2_msgdef, write_sequence_mcap
from datasets.mcap_scan import scan_mcap
from datasets.memory import random_sequence
from datasets.open import open_sequence
from datasets.rigs import small_rig_calibration
from slam.core.errors import InputError
from tools.cli import main as slam_main

N_FRAMES = 40


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory):
    """A sequence written with small chunks, so damage hits only part of it."""
    seq = random_sequence(num_frames=N_FRAMES, width=96, height=72, seed=11)
    path = tmp_path_factory.mktemp("bad") / "good.mcap"
    write_sequence_mcap(seq, path, progress=False, chunk_size_bytes=48 * 1024)
    return seq, path


def _frames_by_time(seq) -> dict:  # type: ignore[no-untyped-def]
    return {f.t_ns: f for f in seq.iter_frames()}


def test_truncated_mcap_keeps_prefix(good, tmp_path: Path) -> None:
    seq, path = good
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    back = McapSequence(cut)
    assert 0.3 * N_FRAMES < back.num_frames < 0.7 * N_FRAMES
    # the loss is counted in frames and seconds against the totals the header announced
    lost = N_FRAMES - back.num_frames
    t_last = back.frame_times_ns()[-1]
    lost_s = (seq.end_ns() - t_last) * 1e-9
    note = [w for w in back.warnings if w.startswith("file is truncated")]
    assert len(note) == 1 and note[0].endswith(
        f": {lost} of {N_FRAMES} frames ({100 * lost / N_FRAMES:.0f} %) and {lost_s:.2f} s of "
        f"{seq.duration_ns * 1e-9:.2f} s are lost, everything after t = {t_last * 1e-9:.3f} s "
        "(totals from the file's header metadata)"
    )
    with pytest.raises(InputError, match="file is truncated .*run without --strict"):
        McapSequence(cut, strict=True)
    # the prefix that was read is exact; calibration survived (written first)
    ref = _frames_by_time(seq)
    np.testing.assert_array_equal(back.frame_times_ns(), seq.frame_times_ns()[: back.num_frames])
    for f in back.iter_frames():
        assert np.array_equal(f.left, ref[f.t_ns].left) and np.array_equal(
            f.right, ref[f.t_ns].right
        )
    assert back.calibration.to_dict() == seq.calibration.to_dict()
    n_imu = back.num_imu
    assert 0 < n_imu < seq.num_imu
    np.testing.assert_array_equal(back.imu().gyro_rad_s, seq.imu().gyro_rad_s[:n_imu])
    # the mcap library's indexed reader cannot open the same file at all
    from mcap.reader import make_reader

    with open(cut, "rb") as fh, pytest.raises(Exception):  # noqa: B017, PT011
        list(make_reader(fh).iter_messages())


def test_corrupt_chunks_are_skipped(good, tmp_path: Path) -> None:
    """One damaged image chunk and one damaged IMU/pose chunk: both skipped with warnings."""
    seq, path = good
    scan = scan_mcap(path)
    images = [c for c in scan.chunks if not c.validated]  # image-only chunks, read lazily
    small = [c for c in scan.chunks if c.validated]
    assert len(images) > 6 and len(small) > 3
    data = bytearray(path.read_bytes())
    for ref in (images[len(images) // 2], small[len(small) // 2]):
        mid = ref.data_offset + ref.data_length // 2
        data[mid : mid + 64] = bytes(64)  # zero 64 bytes inside the compressed chunk
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    back = McapSequence(bad)
    # opening reads the small chunks: the damaged one is reported, and the IMU hole it leaves
    assert sum(w.startswith("corrupt chunk at byte") for w in back.warnings) == 1
    assert any("/imu0: 1 gap(s)" in w for w in back.warnings)
    np.testing.assert_array_equal(
        back.imu().gyro_rad_s, seq.imu().gyro_rad_s[np.isin(seq.imu().t_ns, back.imu().t_ns)]
    )
    # image chunks are CRC-checked when read: frames in the damaged one are skipped
    ref_frames = _frames_by_time(seq)
    frames = list(back.iter_frames())
    assert N_FRAMES - 6 <= len(frames) < N_FRAMES
    for f in frames:  # everything outside the bad chunk is intact
        assert np.array_equal(f.left, ref_frames[f.t_ns].left)
        assert np.array_equal(f.right, ref_frames[f.t_ns].right)
    assert sum(w.startswith("corrupt chunk at byte") for w in back.warnings) == 2
    assert any("frame(s) in corrupt chunks were skipped" in w for w in back.warnings)
    # verify() (what `slam info` runs) finds the image chunk without iterating, and drops its
    # frames: counts and times are those a run gets
    checked = McapSequence(bad)
    assert checked.num_frames == N_FRAMES
    assert checked.verify() == 1
    assert checked.num_frames == len(frames)
    n_warnings = len(checked.warnings)
    assert checked.verify() == 1 and len(checked.warnings) == n_warnings  # once is enough
    np.testing.assert_array_equal(checked.frame_times_ns(), [f.t_ns for f in frames])
    assert [f.t_ns for f in checked.iter_frames()] == [f.t_ns for f in frames]
    skipped = N_FRAMES - len(frames)
    assert any(w.startswith(f"{skipped} frame(s) in corrupt chunks will be skipped") for w in
               checked.warnings)  # fmt: skip
    with pytest.raises(InputError, match="corrupt chunk at byte .*without --strict"):
        McapSequence(bad, strict=True)


def test_info_reports_what_a_run_gets(
    good, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`slam info` on a file with a corrupt image chunk: the frames a run gets, and the gap."""
    seq, path = good
    scan = scan_mcap(path)
    images = [c for c in scan.chunks if not c.validated]
    ref = images[len(images) // 2]
    data = bytearray(path.read_bytes())
    mid = ref.data_offset + ref.data_length // 2
    data[mid : mid + 64] = bytes(64)
    bad = tmp_path / "corrupt.mcap"
    bad.write_bytes(bytes(data))
    kept = [f.t_ns for f in McapSequence(bad).iter_frames()]
    assert slam_main(["info", str(bad)]) == 0
    out = capsys.readouterr().out
    assert f"  frames        {len(kept)} stereo" in out
    assert "  gaps     frames: 1 gap(s)" in out
    assert f"{N_FRAMES - len(kept)} frame(s) in corrupt chunks will be skipped" in out


def _cut_raw(tmp_path: Path, fraction: float) -> Path:
    """A file without our header metadata (a foreign recording), cut to ``fraction``."""
    ms = 1_000_000
    path = tmp_path / "raw.mcap"
    _write_raw(path, [k * 50 * ms for k in range(40)], [k * 5 * ms for k in range(400)])
    data = path.read_bytes()
    cut = tmp_path / f"raw_cut{fraction}.mcap"
    cut.write_bytes(data[: int(len(data) * fraction)])
    return cut


def test_truncation_without_totals_gives_a_lower_bound(tmp_path: Path) -> None:
    full = scan_mcap(_cut_raw(tmp_path, 1.0))
    assert full.recorded is not None and full.recorded.counts["/cam0/image_raw"] == 40
    assert full.recorded.source == "the file's summary statistics"
    scan = scan_mcap(_cut_raw(tmp_path, 0.5))  # the cut goes through the only chunk
    assert scan.recorded is None and scan.cut_chunk_ns == (0, 1_995_000_000)
    assert scan.truncation_note("/cam0/image_raw", "frames") == (
        f"file is truncated (its last {scan.lost_bytes} bytes could not be read); no frames; "
        "the file's account of what it holds (summary, metadata) did not survive, so the loss "
        "cannot be counted; at least 2.00 s are lost: the chunk the cut went through ran to "
        "t = 1.995 s"
    )
    # cut inside the summary: the data section is whole, nothing is lost
    tail = scan_mcap(_cut_raw(tmp_path, 0.99))
    assert tail.lost_bytes > 0 and not tail.lost_data and len(tail.msg_log_ns) == 440
    assert tail.truncation_note() is not None and "no message is lost" in tail.truncation_note()


def test_frames_lost_in_a_corrupt_chunk_are_counted(tmp_path: Path) -> None:
    """A foreign file (images in ordinary chunks): the frames a corrupt chunk held are counted
    against the summary's statistics."""
    ms = 1_000_000
    path = tmp_path / "chunks.mcap"
    frames = [k * 50 * ms for k in range(40)]
    _write_raw(path, frames, [k * 5 * ms for k in range(400)], chunk_size=4096)
    scan = scan_mcap(path)
    in_chunk = scan.msg_chunk == 3  # images are written first: chunk 3 holds only images
    assert in_chunk.sum() > 1 and set(scan.msg_channel[in_chunk]) == set(
        scan.channel_ids("/cam0/image_raw")
    )
    victim = scan.chunks[3]
    data = bytearray(path.read_bytes())
    mid = victim.data_offset + victim.data_length // 2
    data[mid : mid + 32] = bytes(32)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    seq = McapSequence(bad)
    lost = 40 - seq.num_frames
    assert lost == in_chunk.sum()
    assert (
        f"{lost} of 40 frames were in the corrupt chunk(s) and are lost (totals from the "
        "file's summary statistics)" in seq.warnings
    )


def test_truncated_rosbag2_counts_from_metadata_yaml(tmp_path: Path) -> None:
    """A cut ROS 2 bag: the totals come from the bag folder's metadata.yaml."""
    bag = tmp_path / "bag"
    bag.mkdir()
    ms = 1_000_000
    path = bag / "bag_0.mcap"
    _write_raw(path, [k * 50 * ms for k in range(40)], [k * 5 * ms for k in range(400)])
    data = path.read_bytes()  # one chunk: the cut loses every message
    path.write_bytes(data[: int(len(data) * 0.5)])
    (bag / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n"
        "  version: 5\n"
        "  storage_identifier: mcap\n"
        "  duration:\n    nanoseconds: 1995000000\n"
        "  starting_time:\n    nanoseconds_since_epoch: 0\n"
        "  message_count: 440\n"
        "  topics_with_message_count:\n"
        "    - topic_metadata:\n        name: /cam0/image_raw\n        type: "
        "sensor_msgs/msg/Image\n      message_count: 40\n"
        "    - topic_metadata:\n        name: /imu0\n        type: sensor_msgs/msg/Imu\n"
        "      message_count: 400\n"
        "  relative_file_paths:\n    - bag_0.mcap\n"
    )
    scan = scan_mcap(path)
    assert scan.recorded is not None and scan.recorded.source == "the bag's metadata.yaml"
    assert scan.truncation_note("/cam0/image_raw", "frames") == (
        f"file is truncated (its last {scan.lost_bytes} bytes could not be read): 40 of 40 "
        "frames (100 %) and 2.00 s of 2.00 s are lost, everything from the start (totals from "
        "the bag's metadata.yaml)"
    )


def _write_raw(
    path: Path,
    frame_times: list[int],
    imu_times: list[int],
    *,
    encoding_override: bytes | None = None,
    calibration: bool = True,
    chunk_size: int = 1024 * 1024,
) -> None:
    """Write a file message by message, in the given (possibly bad) order."""
    cal = small_rig_calibration(32, 24, stereo=False)
    rng = np.random.default_rng(0)
    with open(path, "wb") as fh:
        w = Writer(fh, compression=CompressionType.ZSTD, chunk_size=chunk_size)
        w.start(profile="ros2", library="test")
        if calibration:
            w.add_metadata("pyvislam.calibration", {"json": json.dumps(cal.to_dict())})
        s_img = w.register_schema(
            "sensor_msgs/msg/Image", "ros2msg", ros2_msgdef("sensor_msgs/msg/Image")
        )
        s_imu = w.register_schema(
            "sensor_msgs/msg/Imu", "ros2msg", ros2_msgdef("sensor_msgs/msg/Imu")
        )
        c_img = w.register_channel("/cam0/image_raw", "cdr", s_img)
        c_imu = w.register_channel("/imu0", "cdr", s_imu)
        for t in frame_times:
            data = cdr.encode_image_mono8(t, "cam0", rng.integers(0, 256, (24, 32), dtype=np.uint8))
            if encoding_override is not None:
                data = data.replace(b"mono8", encoding_override)
            w.add_message(c_img, log_time=t, data=data, publish_time=t)
        for t in imu_times:
            data = cdr.encode_imu(t, "imu0", rng.normal(size=3), rng.normal(size=3))
            w.add_message(c_imu, log_time=t, data=data, publish_time=t)
        w.finish()


def test_out_of_order_and_duplicates_counted(tmp_path: Path) -> None:
    ms = 1_000_000
    frames = [0, 50 * ms, 150 * ms, 100 * ms, 100 * ms, 200 * ms]  # 1 out of order, 1 duplicate
    imu = [k * 5 * ms for k in range(41)]
    imu[10], imu[11] = imu[11], imu[10]  # swapped pair
    imu.insert(20, imu[20])  # duplicate
    path = tmp_path / "order.mcap"
    _write_raw(path, frames, imu)
    seq = McapSequence(path)
    assert seq.num_frames == 5
    assert np.all(np.diff(seq.frame_times_ns()) > 0)
    assert seq.num_imu == 41 and np.all(np.diff(seq.imu().t_ns) > 0)
    text = " | ".join(seq.warnings)
    assert (
        "/cam0/image_raw: 1 out of time order (sorted), 1 with duplicate timestamps (dropped)"
        in text
    )
    assert "/imu0: 1 out of time order (sorted), 1 with duplicate timestamps (dropped)" in text


def test_imu_gap_is_warned(tmp_path: Path) -> None:
    ms = 1_000_000
    imu = [k * 5 * ms for k in range(200) if not 80 <= k < 120]  # 200 ms hole
    path = tmp_path / "gap.mcap"
    _write_raw(path, [0, 50 * ms], imu)
    seq = McapSequence(path)
    gap = [w for w in seq.warnings if "gap" in w]
    assert len(gap) == 1 and "/imu0: 1 gap(s)" in gap[0] and "longest 205.0 ms" in gap[0]


def test_unknown_encoding_lists_topics(tmp_path: Path) -> None:
    path = tmp_path / "enc.mcap"
    _write_raw(path, [0, 50_000_000], [0], encoding_override=b"yuv42")
    with pytest.raises(InputError, match="'yuv42'") as err:
        McapSequence(path)
    assert "/cam0/image_raw [sensor_msgs/msg/Image" in str(err.value) and "/imu0" in str(err.value)


def test_missing_topic_lists_topics(good) -> None:
    _seq, path = good
    with pytest.raises(InputError) as err:
        open_sequence(path, right_topic="/stereo/right")
    msg = str(err.value)
    assert "/stereo/right not found" in msg
    for topic in ("/cam0/image_raw", "/cam1/image_raw", "/imu0", "/groundtruth/pose"):
        assert topic in msg


def test_missing_calibration_says_how(tmp_path: Path) -> None:
    path = tmp_path / "nocal.mcap"
    _write_raw(path, [0, 50_000_000], [0], calibration=False)
    with pytest.raises(InputError, match="--camchain camchain.yaml --imu-yaml imu.yaml"):
        open_sequence(path)


def test_missing_image_file_skips_its_frame(tmp_path: Path) -> None:
    from test_euroc import write_asl_folder

    ref = write_asl_folder(tmp_path)
    victim = sorted((tmp_path / "mav0" / "cam1" / "data").iterdir())[3]
    victim.unlink()
    seq = open_sequence(tmp_path)
    t_ref = ref.frame_times_ns()  # type: ignore[attr-defined]
    np.testing.assert_array_equal(seq.frame_times_ns(), np.delete(t_ref, 3))
    assert [f.t_ns for f in seq.iter_frames()] == list(np.delete(t_ref, 3))
    assert (
        f"1 frame(s) skipped: image file missing: cam1/{victim.name} (listed in data.csv; "
        "--strict refuses the folder instead)" in seq.warnings
    )
    with pytest.raises(InputError, match=f"image file missing: .*{victim.name}.*--strict"):
        open_sequence(tmp_path, strict=True)
    for f in (tmp_path / "mav0" / "cam0" / "data").iterdir():
        f.unlink()
    with pytest.raises(InputError, match="none of the 6 frames listed in .*cam0.data.csv"):
        open_sequence(tmp_path)


def test_unrecognised_paths(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("hello")
    with pytest.raises(InputError, match="not a sequence"):
        open_sequence(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="no such file"):
        open_sequence(tmp_path / "absent.mcap")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "empty.mcap").write_bytes(b"")
    with pytest.raises(InputError, match=r"empty.mcap is empty \(0 bytes\)"):
        open_sequence(tmp_path / "sub" / "empty.mcap")
    with pytest.raises(InputError, match="not a sequence"):
        open_sequence(tmp_path)


def test_ros1_bag_gets_a_conversion_hint(shared_data: Path) -> None:
    from conftest import require

    bag = require(shared_data / "trajectories" / "evo_testdata" / "ROS_example.bag")
    with pytest.raises(InputError, match="ROS 1 bag.*rosbags-convert"):
        open_sequence(bag)


def test_cli_reports_one_line(good, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _seq, path = good
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    assert slam_main(["info", str(cut)]) == 0
    out = capsys.readouterr().out
    assert "file is truncated" in out and "frames" in out
    rc = slam_main(["convert", str(cut), str(tmp_path / "x.mcap"), "--right-topic", "/nope", "-q"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "/nope not found" in err
    assert not (tmp_path / "x.mcap").exists()
