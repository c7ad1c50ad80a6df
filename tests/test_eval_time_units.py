"""Times in another unit than the file's format says (ns in a TUM file, ...) are named, with the
option that fixes them, in one line; passing that option gives the same numbers as seconds."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from slam.core.errors import InputError
from slam.evaluation import io as evio
from slam.evaluation import timeunits
from slam.evaluation.timeunits import TimeSpan
from tools.cli import main

T0_NS = 1_403_715_524_912_143_000  # EuRoC V1_02's first ground-truth time


def _poses(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 2.0 * np.pi, n)
    xyz = np.column_stack([np.cos(t), np.sin(t), 0.1 * t]) + rng.normal(scale=0.01, size=(n, 3))
    q = np.tile([0.0, 0.0, 0.0, 1.0], (n, 1))  # x, y, z, w
    return xyz, q


def _tum(path: Path, times: list[str], xyz: np.ndarray, q: np.ndarray) -> Path:
    rows = [
        " ".join([t, *map(repr, p.tolist()), *map(repr, r.tolist())])
        for t, p, r in zip(times, xyz, q)
    ]
    path.write_text("\n".join(rows) + "\n")
    return path


def _pair(tmp_path: Path, unit: str, start_ns: int = T0_NS) -> tuple[Path, Path, Path]:
    """Reference (EuRoC csv, ns), the estimate in seconds, and the same estimate in ``unit``."""
    n = 60
    t_ns = start_ns + np.arange(n, dtype=np.int64) * 50_000_000
    xyz, q = _poses(n)
    ref = tmp_path / "gt.csv"
    ref.write_text(
        "\n".join(
            ",".join([str(t), *map(repr, p.tolist()), "1.0", "0.0", "0.0", "0.0"])
            for t, p in zip(t_ns.tolist(), xyz)
        )
        + "\n"
    )
    est_xyz = xyz + 0.02
    per_ns = {"s": 1_000_000_000, "ms": 1_000_000, "us": 1_000, "ns": 1}[unit]
    in_s = _tum(
        tmp_path / "est_s.txt", [evio.ns_to_seconds_str(t) for t in t_ns.tolist()], est_xyz, q
    )
    if per_ns == 1:
        times = [str(t) for t in t_ns.tolist()]
    else:
        times = [f"{t // per_ns}.{t % per_ns:0{len(str(per_ns)) - 1}d}" for t in t_ns.tolist()]
    in_unit = _tum(tmp_path / f"est_{unit}.txt", times, est_xyz, q)
    return ref, in_s, in_unit


@pytest.mark.parametrize(
    "unit, name", [("ns", "nanoseconds"), ("us", "microseconds"), ("ms", "milliseconds")]
)
def test_epoch_times_in_another_unit_are_named_with_the_option(
    tmp_path: Path, capsys, unit: str, name: str
) -> None:
    ref, in_s, in_unit = _pair(tmp_path, unit)
    assert main(["eval", "ape", str(ref), str(in_unit)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"slam eval: error: estimate {in_unit}: timestamps look like {name}")
    assert err[0].endswith(
        f"not seconds, given the reference's 1403715524.912..1403715527.862 s: pass --est-time-unit {unit}"
    )
    assert "Traceback" not in err[0]
    # the option named gives the numbers of the file in seconds, to the last digit
    out_s, out_unit = tmp_path / "s.json", tmp_path / "u.json"
    assert main(["eval", "ape", str(ref), str(in_s), "--json", str(out_s)]) == 0
    assert (
        main(
            [
                "eval",
                "ape",
                str(ref),
                str(in_unit),
                "--est-time-unit",
                unit,
                "--json",
                str(out_unit),
            ]
        )
        == 0
    )
    a, b = json.loads(out_s.read_text()), json.loads(out_unit.read_text())
    assert a["association"]["pairs"] == b["association"]["pairs"] == 60
    assert a["stats"] == b["stats"]


@pytest.mark.parametrize("unit, name", [("ms", "milliseconds"), ("ns", "nanoseconds")])
def test_times_from_zero_in_another_unit(tmp_path: Path, capsys, unit: str, name: str) -> None:
    """Both from 0: the ranges overlap at the start (one pair: 'se3 alignment needs at least
    3 pose pairs' before), but the estimate's is 1000 or 1e9 times longer."""
    ref, _, in_unit = _pair(tmp_path, unit, start_ns=0)
    xyz, q = _poses(60)
    tum_ref = _tum(tmp_path / "gt.txt", [f"{0.05 * k:.2f}" for k in range(60)], xyz, q)
    for r in (ref, tum_ref):
        assert main(["eval", "ape", str(r), str(in_unit)]) == 2
        err = capsys.readouterr().err.strip()
        assert f"look like {name} (first 0)" in err and err.endswith(f"--est-time-unit {unit}")
        assert main(["eval", "ape", str(r), str(in_unit), "--est-time-unit", unit]) == 0


def test_reference_in_nanoseconds_names_the_reference_option(tmp_path: Path, capsys) -> None:
    _, in_s, in_ns = _pair(tmp_path, "ns")
    assert main(["eval", "ape", str(in_ns), str(in_s)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"slam eval: error: reference {in_ns}: timestamps look like nanoseconds")
    assert err.endswith("pass --ref-time-unit ns")
    assert main(["eval", "ape", str(in_ns), str(in_s), "--ref-time-unit", "ns"]) == 0


def test_euroc_csv_in_seconds(tmp_path: Path, capsys) -> None:
    _, in_s, _ = _pair(tmp_path, "s")
    csv = tmp_path / "est.csv"
    csv.write_text(
        "".join(
            ",".join([ln.split()[0], *ln.split()[1:4], "1", "0", "0", "0"]) + "\n"
            for ln in in_s.read_text().splitlines()
        )
    )
    assert main(["eval", "ape", str(in_s), str(csv)]) == 2
    err = capsys.readouterr().err.strip()
    assert "look like seconds (first 1.4037e+09), not nanoseconds" in err
    assert err.endswith("pass --est-time-unit s")
    assert main(["eval", "ape", str(in_s), str(csv), "--est-time-unit", "s"]) == 0
    with pytest.raises(InputError) as alone:  # without a reference to compare with
        evio.read_trajectory(csv, role="estimate")
    assert str(alone.value) == (
        f"estimate {csv}:2: times 1403715524.912143000 and 1403715524.962143000 fall in the same "
        "nanosecond when read as nanoseconds; pass --est-time-unit with the file's unit (s, ms, us)"
    )


def test_a_short_estimate_inside_a_long_reference_is_left_alone() -> None:
    ref = TimeSpan(0.0, 100.0, 20_001, "s")  # 200 Hz for 100 s
    short = TimeSpan(0.0, 0.1, 3, "s")  # 3 poses at 20 Hz
    assert timeunits.likely_unit(ref, short) is None
    assert timeunits.likely_unit(ref, TimeSpan(0.0, 100_000.0, 2_001, "s")) == ("estimate", "ms")
    epoch_ns = TimeSpan(1.4e18, 1.4e18 + 1e11, 2_001, "s")  # overflowing span, as read
    assert timeunits.likely_unit(TimeSpan(1.4e9, 1.4e9 + 100, 20_001, "s"), epoch_ns) == (
        "estimate",
        "ns",
    )
    bag = TimeSpan(1.4e18, 1.4e18 + 1e11, 2_001, "s", adjustable=False)
    assert timeunits.likely_unit(TimeSpan(1.4e9, 1.4e9 + 100, 20_001, "s"), bag) is None


def test_overflow_alone_names_the_option_and_units_apply_to_text_files_only(tmp_path: Path) -> None:
    _, _, in_ns = _pair(tmp_path, "ns")
    with pytest.raises(InputError) as err:
        evio.read_trajectory(in_ns, role="estimate")
    assert str(err.value) == (
        f"estimate {in_ns}: timestamps 1.4037e+18..1.4037e+18 are too large to be seconds; "
        "pass --est-time-unit with the file's unit (ms, us, ns)"
    )
    src = evio.read_trajectory(in_ns, time_unit="ns")
    assert src.trajectory.t_ns[0] == T0_NS
    np.testing.assert_array_equal(src.seconds, src.trajectory.t_ns / 1e9)
    seq = tmp_path / "MH_01" / "mav0" / "state_groundtruth_estimate0"
    seq.mkdir(parents=True)
    (seq / "data.csv").write_text("1,0,0,0,1,0,0,0\n2,1,0,0,1,0,0,0\n")
    with pytest.raises(InputError, match="time unit applies to text files"):
        evio.read_trajectory(tmp_path / "MH_01", time_unit="ns")
    with pytest.raises(InputError, match="unknown time unit 'h'"):
        evio.read_trajectory(in_ns, time_unit="h")


def test_seconds_to_ns_in_every_unit() -> None:
    assert evio.seconds_to_ns("12.5", "ms") == 12_500_000
    assert evio.seconds_to_ns("12.5", "us") == 12_500
    assert evio.seconds_to_ns("12.7", "ns") == 12  # below 1 ns: truncated
    assert evio.seconds_to_ns("-3.25", "s") == -3_250_000_000
    assert evio.seconds_to_ns("1.5e3", "ms") == 1_500_000_000
