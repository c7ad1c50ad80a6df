"""Bad inputs give one-line errors naming file and line, and a non-zero CLI exit; formats round-trip."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from slam.core.errors import InputError
from slam.core.trajectory import Trajectory
from slam.evaluation import io as evio
from slam.evaluation.associate import associate
from tools.cli import main

GOOD = "1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n3.0 2 1 0 0 0 0 1\n4.0 3 1 1 0 0 0 1\n"


def _write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "text, line, words",
    [
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n", 2, "7 values"),
        ("# c\n1.0 0 0 0 0 0 0 1\n2.0 0 x 0 0 0 0 1\n", 3, "'x' is not a number"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 nan 0 0 0 0 1\n", 2, "NaN"),
        ("1.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n", 2, "duplicate timestamp"),
        ("2.0 0 0 0 0 0 0 1\n1.0 1 0 0 0 0 0 1\n", 2, "backwards"),
        ("1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 0.5\n", 2, "quaternion norm"),
    ],
)
def test_bad_lines_name_file_and_line(
    tmp_path: Path, text: str, line: int, words: str, capsys
) -> None:
    bad = _write(tmp_path, "bad.txt", text)
    good = _write(tmp_path, "good.txt", GOOD)
    with pytest.raises(InputError) as err:
        evio.read_trajectory(bad, "tum")
    msg = str(err.value)
    assert f"{bad}:{line}:" in msg and words in msg and "\n" not in msg
    assert main(["eval", "ape", str(good), str(bad)]) == 2
    stderr = capsys.readouterr().err.strip().splitlines()
    assert len(stderr) == 1 and f"{bad}:{line}" in stderr[0]


def test_empty_and_unknown(tmp_path: Path, capsys) -> None:
    empty = _write(tmp_path, "empty.txt", "# only a comment\n\n")
    with pytest.raises(InputError, match="empty"):
        evio.read_trajectory(empty)
    odd = _write(tmp_path, "odd.txt", "1 2 3 4 5\n")
    with pytest.raises(InputError, match=r"odd.txt:1: unknown format: 5 columns"):
        evio.read_trajectory(odd)
    binary = tmp_path / "x.bin"
    binary.write_bytes(b"\x00\x01\x02")
    with pytest.raises(InputError, match="unknown format"):
        evio.read_trajectory(binary)
    assert main(["eval", "ape", str(empty), str(odd)]) == 2
    assert main(["eval", "ape", str(tmp_path / "missing.txt"), str(odd)]) == 2


def test_near_unit_quaternion_normalised_with_warning(tmp_path: Path, caplog) -> None:
    p = _write(tmp_path, "q.txt", "1.0 0 0 0 0 0 0 1.0005\n2.0 1 0 0 0 0 0 1\n")
    src = evio.read_trajectory(p)
    np.testing.assert_allclose(np.linalg.norm(src.trajectory.q_wxyz, axis=1), 1.0, atol=1e-15)
    assert any("normalised 1 non-unit" in w for w in src.warnings)
    assert "q.txt:1" in caplog.text


def test_dedupe_keeps_first_or_last(tmp_path: Path) -> None:
    p = _write(tmp_path, "d.txt", "1.0 0 0 0 0 0 0 1\n1.0 5 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n")
    assert evio.read_trajectory(p, duplicates="first").trajectory.positions_m[0, 0] == 0.0
    assert evio.read_trajectory(p, duplicates="last").trajectory.positions_m[0, 0] == 5.0


def test_sort_puts_rows_in_time_order_and_quiet_only_keeps_the_warnings(
    tmp_path: Path, caplog
) -> None:
    """The datasets' reading of ground truth: sorted, first of repeated times, nothing logged."""
    from datasets.euroc import read_trajectory_file

    text = "2.0 1 0 0 0 0 0 1\n1.0 0 0 0 0 0 0 1.0005\n2.0 5 0 0 0 0 0 1\n3.0 2 0 0 0 0 0 1\n"
    p = _write(tmp_path, "u.txt", text)
    with pytest.raises(InputError, match="backwards"):
        evio.read_trajectory(p)
    src = evio.read_trajectory(p, duplicates="first", sort=True, quiet=True)
    np.testing.assert_array_equal(
        src.trajectory.t_ns, [1_000_000_000, 2_000_000_000, 3_000_000_000]
    )
    np.testing.assert_array_equal(src.trajectory.positions_m[:, 0], [0.0, 1.0, 2.0])
    assert len(src.warnings) == 3 and "u.txt:3" in src.warnings[1]  # sorted, dropped, normalised
    assert caplog.text == ""
    traj = read_trajectory_file(p)
    np.testing.assert_array_equal(traj.positions_m, src.trajectory.positions_m)
    assert caplog.text == ""
    evio.read_trajectory(p, duplicates="first", sort=True)
    assert "sorted the poses by time (1 went back in time)" in caplog.text


def test_non_overlapping_ranges_and_ns_hint(tmp_path: Path) -> None:
    ref = evio.read_trajectory(_write(tmp_path, "ref.txt", GOOD))
    est = evio.read_trajectory(
        _write(tmp_path, "late.txt", "101.0 0 0 0 0 0 0 1\n102.0 1 0 0 0 0 0 1\n")
    )
    with pytest.raises(InputError, match="do not overlap.*--t-offset"):
        associate(ref, est)
    ns = "1000000000.5 0 0 0 0 0 0 1\n2000000000.5 1 0 0 0 0 0 1\n"  # nanoseconds in a TUM file
    est_ns = evio.read_trajectory(_write(tmp_path, "ns.txt", ns))
    with pytest.raises(
        InputError,
        match=r"factor of ~[0-9.e+]+: .*ns.txt probably holds nanoseconds .*: pass --est-time-unit ns$",
    ):
        associate(ref, est_ns)


def test_formats_round_trip_and_detection(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    n = 50
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1)[:, None]
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    traj = Trajectory(
        t_ns=1_403_715_273_262_142_976 + np.arange(n, dtype=np.int64) * 50_000_000,
        positions_m=rng.normal(size=(n, 3)),
        q_wxyz=q,
    )
    evio.write_tum(tmp_path / "a.tum", traj)
    evio.write_euroc_csv(tmp_path / "a.csv", traj)
    evio.write_kitti(tmp_path / "a_kitti.txt", traj, tmp_path / "a_kitti_times.txt")
    run = tmp_path / "run1"
    run.mkdir()
    evio.write_tum(run / "trajectory.tum", traj)
    seq = tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0"
    seq.mkdir(parents=True)
    evio.write_euroc_csv(seq / "data.csv", traj)
    for path, fmt in [
        (tmp_path / "a.tum", "tum"),
        (tmp_path / "a.csv", "euroc"),
        (tmp_path / "a_kitti.txt", "kitti"),
        (run, "run"),
        (tmp_path / "MH_01", "sequence"),
    ]:
        assert evio.detect_format(path) == fmt
        src = evio.read_trajectory(path)
        assert src.timed
        np.testing.assert_array_equal(src.trajectory.t_ns, traj.t_ns)
        np.testing.assert_allclose(src.trajectory.positions_m, traj.positions_m, atol=1e-12)
        np.testing.assert_allclose(src.trajectory.q_wxyz, traj.q_wxyz, atol=1e-12)


def test_euroc_header_with_xyzw_order(tmp_path: Path) -> None:
    text = "#t,x,y,z,qx,qy,qz,qw\n1000,0,0,0,0,0,0,1\n2000,1,0,0,0,0,0,1\n"
    src = evio.read_trajectory(_write(tmp_path, "e.csv", text))
    np.testing.assert_allclose(src.trajectory.q_wxyz[0], [1, 0, 0, 0])


def test_bag_topics(shared_data: Path) -> None:
    from conftest import require

    bag = require(shared_data / "trajectories" / "evo_testdata" / "nav2_turtlebot.mcap")
    with pytest.raises(InputError, match="several pose topics"):
        evio.read_trajectory(bag, role="estimate")
    odom = evio.read_trajectory(bag, topic="/odom")
    assert len(odom) == 2639 and odom.format == "bag"
    evo_fi = pytest.importorskip("evo.tools.file_interface")
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        ref = evo_fi.read_bag_trajectory(reader, "/odom")
    np.testing.assert_allclose(odom.seconds, ref.timestamps, rtol=0, atol=0)
    np.testing.assert_allclose(odom.trajectory.positions_m, ref.positions_xyz, rtol=0, atol=0)


def test_seconds_parsing_is_exact() -> None:
    tokens = ["12.5", "-0.5", "1403715273.262142976", "7", "1.403715572012143135e+09", "3."]
    t_ns = evio._times_ns_from_seconds(Path("x"), tokens, list(range(1, 7)))
    assert t_ns.tolist() == [
        12_500_000_000,
        -500_000_000,
        1_403_715_273_262_142_976,
        7_000_000_000,
        round(1.403715572012143135e09 * 1e9),
        3_000_000_000,
    ]
