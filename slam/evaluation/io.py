"""Read and write trajectories in every format ``slam eval`` accepts, and detect which one a path is.

Formats (``FORMATS``):
  tum       ``t x y z qx qy qz qw`` per line, t in seconds, whitespace separated, ``#`` comments
  euroc     csv, ``t_ns, px, py, pz, qw, qx, qy, qz[, ...]``: the EuRoC ground-truth layout
            (17 columns) and the plain estimate layout (8 columns); a header naming ``qx..qw``
            in x,y,z,w order is honoured
  kitti     12 numbers per line (3x4 world_from_body, row-major); times from a times file
            (``--ref-times``/``--est-times`` or a sibling ``<stem>_times.txt``), else untimed
  bag       ROS 2 bag (MCAP file or rosbag2 folder) or ROS 1 bag: PoseStamped,
            PoseWithCovarianceStamped, Odometry or TransformStamped topics (header stamps)
  run       a ``slam run`` output folder (reads its ``trajectory.tum``)
  sequence  a sequence's ground truth: an EuRoC folder, or our MCAP with /groundtruth/pose,
            through ``datasets.open.open_sequence`` when that module is present

Every problem raises :class:`slam.core.errors.InputError` with ``file:line: what is wrong``.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam.core.errors import InputError
from slam.core.trajectory import Trajectory
from slam.evaluation import lie
from slam.evaluation.timeunits import (
    NS_DIGITS,
    PER_SECOND,
    UNIT_NAMES,
    TimeSpan,
    TimeUnitError,
    check_unit,
)

log = logging.getLogger(__name__)

FORMATS = ("tum", "euroc", "kitti", "bag", "run", "sequence")

#: A quaternion whose norm is further than this from 1 is refused (it is not a rotation).
QUAT_NORM_REFUSE = 1e-2
#: Quaternions with |norm - 1| above this (and below the refusal bound) are normalised, with a warning.
QUAT_NORM_WARN = 1e-6

SUPPORTED_ROS_TYPES = (
    "geometry_msgs/msg/PoseStamped",
    "geometry_msgs/msg/PoseWithCovarianceStamped",
    "geometry_msgs/msg/TransformStamped",
    "nav_msgs/msg/Odometry",
)
GROUND_TRUTH_TOPIC = "/groundtruth/pose"


@dataclass(frozen=True, eq=False)
class PoseSource:
    """A trajectory as read from a file, plus what evaluation needs beyond :class:`Trajectory`.

    ``stamps_s`` holds the times as the reference tool parses them (float seconds), so that
    nearest-time association picks the very same pairs even at exact ties.
    ``world_from_body`` keeps the (N, 4, 4) poses exactly as read (KITTI rows are not
    re-orthonormalised), so metrics see the same numbers as the reference tools. ``timed`` is
    False for KITTI poses without a times file: such poses pair by index only.
    """

    trajectory: Trajectory
    world_from_body: np.ndarray
    name: str
    path: str
    format: str
    timed: bool = True
    warnings: list[str] = field(default_factory=list)
    stamps_s: np.ndarray | None = None

    @property
    def seconds(self) -> np.ndarray:
        """Float64 seconds computed as evo computes them from the file (for association)."""
        if self.stamps_s is not None:
            return self.stamps_s
        return self.trajectory.t_ns.astype(np.float64) * 1e-9

    def __len__(self) -> int:
        return len(self.trajectory)


# --------------------------------------------------------------------------------------------
# format detection


def detect_format(path: Path) -> str:
    """Guess the format of ``path`` from its kind, name and first data line."""
    if path.is_dir():
        if (path / "trajectory.tum").is_file():
            return "run"
        if (path / "mav0").is_dir() or (path / "state_groundtruth_estimate0").is_dir():
            return "sequence"
        if (path / "metadata.yaml").is_file():
            return "bag"
        raise InputError(
            f"{path}: unknown trajectory folder (expected a `slam run` output with "
            "trajectory.tum, an EuRoC folder with mav0/, or a ROS 2 bag folder); "
            f"use --format {{{','.join(FORMATS)}}}"
        )
    if not path.is_file():
        raise InputError(f"{path}: no such file or folder")
    suffix = path.suffix.lower()
    if suffix in (".mcap", ".bag", ".db3"):
        return "bag"
    with open(path, "rb") as f:
        head = f.read(4096)
    if b"\0" in head:
        raise InputError(
            f"{path}: unknown format (binary file); use --format {{{','.join(FORMATS)}}}"
        )
    text = head.decode("utf-8", errors="replace").lstrip("\ufeff")
    lines = text.splitlines()
    if len(head) == 4096 and len(lines) > 1:
        lines = lines[:-1]  # the last line may be cut
    for number, line in enumerate(lines, start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#") or stripped.startswith("%"):
            continue
        if "," in stripped:
            if stripped[0].isalpha():  # a header row without '#'
                continue
            return "euroc"
        n = len(stripped.split())
        if n == 8:
            return "tum"
        if n == 12:
            return "kitti"
        raise InputError(
            f"{path}:{number}: unknown format: {n} columns (TUM has 8, KITTI 12, EuRoC csv "
            f"is comma separated); use --format {{{','.join(FORMATS)}}}"
        )
    raise InputError(f"{path}: empty file (no pose lines)")


#: The unit of the time column each text format declares (bags and sequences carry their own).
NATIVE_TIME_UNITS = {"tum": "s", "run": "s", "kitti": "s", "euroc": "ns"}


def read_trajectory(
    path: str | Path,
    fmt: str | None = None,
    *,
    topic: str | None = None,
    times_path: str | Path | None = None,
    role: str = "trajectory",
    duplicates: str = "error",
    sort: bool = False,
    quiet: bool = False,
    time_unit: str | None = None,
) -> PoseSource:
    """Read a trajectory in any supported format (``fmt`` None: detect it).

    ``topic`` selects a bag topic; ``times_path`` gives KITTI poses their times; ``role``
    ("reference"/"estimate") only shapes messages and the automatic topic choice;
    ``duplicates`` ("error", "first", "last") says what to do with repeated timestamps;
    ``sort`` (TUM, EuRoC csv, run, bag) puts rows that go back in time in order (stable, with a
    warning) instead of refusing them. What was repaired (rows sorted, duplicates dropped,
    quaternions normalised) is logged as warnings and kept in ``PoseSource.warnings``; ``quiet``
    only keeps it (datasets read their ground truth so: sorted, first of duplicates, quiet).
    ``time_unit`` (s, ms, us, ns) overrides the unit of a text file's time column
    (``NATIVE_TIME_UNITS``); times too large for their unit raise
    :class:`~slam.evaluation.timeunits.TimeUnitError`.
    """
    p = Path(path)
    if not p.exists():
        raise InputError(f"{p}: no such file or folder")
    fmt = fmt or detect_format(p)
    if time_unit is not None:
        check_unit(time_unit)
        if fmt not in NATIVE_TIME_UNITS:
            raise InputError(
                f"{p}: a time unit applies to text files (TUM, EuRoC csv, KITTI times), not to "
                f"{fmt} input, whose stamps carry their unit; drop the time-unit option"
            )
    unit = time_unit or NATIVE_TIME_UNITS.get(fmt, "s")
    try:
        return _read(p, fmt, topic, times_path, role, duplicates, sort, quiet, unit)
    except TimeUnitError as exc:
        if role not in ("reference", "estimate"):
            raise
        flag = "--ref-time-unit" if role == "reference" else "--est-time-unit"
        raise TimeUnitError(f"{role} {exc.what}", exc.span, flag) from None


def _read(
    p: Path,
    fmt: str,
    topic: str | None,
    times_path: str | Path | None,
    role: str,
    duplicates: str,
    sort: bool,
    quiet: bool,
    unit: str,
) -> PoseSource:
    if fmt == "tum":
        return read_tum(p, duplicates, sort=sort, quiet=quiet, time_unit=unit)
    if fmt == "euroc":
        return read_euroc_csv(p, duplicates, sort=sort, quiet=quiet, time_unit=unit)
    if fmt == "kitti":
        return read_kitti(p, times_path, unit)
    if fmt == "run":
        if p.is_dir():
            src = read_tum(p / "trajectory.tum", duplicates, sort=sort, quiet=quiet, time_unit=unit)
            return _renamed(src, p.name or str(p), str(p), "run")
        return read_tum(p, duplicates, sort=sort, quiet=quiet, time_unit=unit)
    if fmt == "bag":
        return read_bag(p, topic, role=role, duplicates=duplicates, sort=sort, quiet=quiet)
    if fmt == "sequence":
        return read_sequence_ground_truth(p)
    raise InputError(f"{p}: unknown format {fmt!r}; choose one of {', '.join(FORMATS)}")


def _renamed(src: PoseSource, name: str, path: str, fmt: str) -> PoseSource:
    return PoseSource(
        src.trajectory, src.world_from_body, name, path, fmt, src.timed, src.warnings, src.stamps_s
    )


# --------------------------------------------------------------------------------------------
# text tables


def _data_lines(path: Path) -> tuple[list[str], list[int], list[str]]:
    """Non-comment, non-blank lines, their 1-based line numbers, and the comment lines."""
    try:
        with open(path, encoding="utf-8-sig") as f:
            text = f.read()
    except UnicodeDecodeError as exc:
        raise InputError(f"{path}: not a text file ({exc.reason})") from None
    except OSError as exc:
        raise InputError(f"{path}: cannot read ({exc.strerror})") from None
    lines: list[str] = []
    numbers: list[int] = []
    comments: list[str] = []
    for number, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s:
            continue
        if s[0] in "#%":
            comments.append(s)
            continue
        lines.append(s)
        numbers.append(number)
    if not lines:
        raise InputError(f"{path}: empty file (no pose lines)")
    return lines, numbers, comments


def _parse_table(
    path: Path,
    lines: list[str],
    numbers: list[int],
    delimiter: str | None,
    columns: int,
    what: str,
    at_least: bool = False,
) -> np.ndarray:
    """Parse lines into an (N, columns) float array; on any error name the offending line.

    ``at_least``: rows may carry more columns (EuRoC ground truth has 17); only the first
    ``columns`` are returned.
    """
    try:
        values = np.loadtxt(lines, delimiter=delimiter, ndmin=2, comments=None)
        if values.shape[1] == columns or (at_least and values.shape[1] >= columns):
            return values[:, :columns]
    except ValueError:
        pass
    expected = f"at least {columns}" if at_least else str(columns)
    first_count = None
    for line, number in zip(lines, numbers):
        tokens = _split(line, delimiter)
        count_ok = len(tokens) >= columns if at_least else len(tokens) == columns
        if first_count is not None and len(tokens) != first_count and count_ok:
            count_ok = False
            expected = str(first_count)
        if not count_ok:
            raise InputError(
                f"{path}:{number}: malformed {what} line: {len(tokens)} values, expected "
                f"{expected}: {line[:60]!r}"
            )
        first_count = len(tokens) if first_count is None else first_count
        for token in tokens:
            try:
                float(token)
            except ValueError:
                raise InputError(
                    f"{path}:{number}: malformed {what} line: {token!r} is not a number"
                ) from None
    raise InputError(f"{path}: malformed {what} file")  # pragma: no cover - caught above


def _split(line: str, delimiter: str | None) -> list[str]:
    return line.split(delimiter) if delimiter else line.split()


def seconds_to_ns(token: str, unit: str = "s") -> int:
    """Exact decimal time string in ``unit`` (default seconds) -> int ns (digits beyond 1 ns
    are truncated)."""
    digits = NS_DIGITS[unit]
    s = token.strip()
    if "e" in s or "E" in s or "n" in s.lower() or "i" in s.lower():
        value = float(s)
        if not np.isfinite(value):
            raise ValueError(token)
        return round(value * 10**digits)
    negative = s.startswith("-")
    s = s.lstrip("+-")
    whole, _, frac = s.partition(".")
    ns = int(whole or "0") * 10**digits + int((frac + "0" * digits)[:digits] or "0")
    return -ns if negative else ns


def _times_ns_from_seconds(
    path: Path, tokens: list[str], numbers: list[int], unit: str = "s"
) -> np.ndarray:
    """Decimal time strings in ``unit`` -> exact int64 ns; one int() per token on the fast path.

    Times beyond int64 nanoseconds (year 2262: e.g. EuRoC's nanoseconds read as seconds) raise
    :class:`TimeUnitError`, which carries the span so that the caller can name the unit.
    """
    digits = NS_DIGITS[unit]
    joined = "".join(tokens)
    try:
        try:
            if "e" in joined or "E" in joined:  # exponent notation: the careful path
                raise ValueError
            # "12.5" -> int("12" + "500000000"); the sign of the whole part carries over
            return np.array(
                [
                    int(w + (f + "0" * digits)[:digits])
                    for w, _, f in (t.partition(".") for t in tokens)
                ],
                dtype=np.int64,
            )
        except ValueError:
            pass  # exponents, "+" signs, or a bad token: the careful path names the line
        out = np.empty(len(tokens), dtype=np.int64)
        for i, tok in enumerate(tokens):
            try:
                out[i] = seconds_to_ns(tok, unit)
            except ValueError:
                raise InputError(f"{path}:{numbers[i]}: bad timestamp {tok!r}") from None
        return out
    except OverflowError:
        raise TimeUnitError(
            f"{path}: timestamps {float(tokens[0]):.5g}..{float(tokens[-1]):.5g} are too large "
            f"to be {UNIT_NAMES[unit]}",
            _span(tokens, unit),
        ) from None


def _span(tokens: list[str], unit: str) -> TimeSpan:
    first, last = float(tokens[0]), float(tokens[-1])
    return TimeSpan(first / PER_SECOND[unit], last / PER_SECOND[unit], len(tokens), unit)


def _times_ns(path: Path, tokens: list[str], numbers: list[int], unit: str) -> np.ndarray:
    """:func:`_times_ns_from_seconds`, refusing distinct times that fall in one nanosecond
    (decimal seconds in a column read as nanoseconds)."""
    t_ns = _times_ns_from_seconds(path, tokens, numbers, unit)
    same = np.flatnonzero(np.diff(t_ns) == 0)
    if len(same) and NS_DIGITS[unit] < 9:
        i = int(same[0])
        if float(tokens[i]) != float(tokens[i + 1]):
            raise TimeUnitError(
                f"{path}:{numbers[i + 1]}: times {tokens[i]} and {tokens[i + 1]} fall in the "
                f"same nanosecond when read as {UNIT_NAMES[unit]}",
                _span(tokens, unit),
            )
    return t_ns


def _check_finite(path: Path, values: np.ndarray, numbers: list[int]) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path}:{numbers[i]}: NaN or infinite value in pose line")


def _check_times(
    path: Path,
    t_ns: np.ndarray,
    numbers: list[int],
    duplicates: str = "error",
    warnings: list[str] | None = None,
) -> np.ndarray:
    """Indices of the rows to keep: refuse backwards time; duplicates per ``duplicates``.

    ``duplicates``: "error" (refuse), "first" or "last" (keep that row of each run of equal
    timestamps, with a warning appended to ``warnings``).
    """
    dt = np.diff(t_ns)
    keep = np.arange(len(t_ns))
    if not len(dt) or (dt > 0).all():
        return keep
    back = dt < 0
    if back.any():
        i = int(np.argmax(back))
        raise InputError(
            f"{path}:{numbers[i + 1]}: timestamp goes backwards (before line {numbers[i]}); "
            "sort the file"
        )
    i = int(np.argmax(dt == 0))
    if duplicates not in ("first", "last"):
        raise InputError(
            f"{path}:{numbers[i + 1]}: duplicate timestamp (same as line {numbers[i]}); "
            "remove it, or pass --dedupe first|last"
        )
    dup = dt == 0
    drop = (
        np.concatenate([dup, [False]]) if duplicates == "last" else np.concatenate([[False], dup])
    )
    if warnings is not None:
        warnings.append(
            f"{path}:{numbers[i + 1]}: dropped {int(dup.sum())} pose(s) with duplicate "
            f"timestamps (kept the {duplicates} of each)"
        )
    return keep[~drop]


def _checked_quaternions(
    path: Path, q_wxyz: np.ndarray, numbers: list[int], warnings: list[str]
) -> np.ndarray:
    """Refuse quaternions far from unit norm; normalise close ones (appended to ``warnings``)."""
    norms = np.linalg.norm(q_wxyz, axis=1)
    off = np.abs(norms - 1.0)
    bad = off > QUAT_NORM_REFUSE
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(
            f"{path}:{numbers[i]}: quaternion norm {norms[i]:.6g} is not 1 "
            f"(|norm-1| > {QUAT_NORM_REFUSE}); is the column order right?"
        )
    warn = off > QUAT_NORM_WARN
    if warn.any():
        i = int(np.argmax(warn))
        warnings.append(
            f"{path}:{numbers[i]}: normalised {int(warn.sum())} non-unit quaternion(s) "
            f"(largest |norm-1| = {off.max():.2g})"
        )
    return q_wxyz / norms[:, None]


def _from_pq(
    path: Path,
    fmt: str,
    t_ns: np.ndarray,
    positions_m: np.ndarray,
    q_wxyz_raw: np.ndarray,
    numbers: list[int],
    duplicates: str = "error",
    stamps_s: np.ndarray | None = None,
    sort: bool = False,
    quiet: bool = False,
) -> PoseSource:
    warnings: list[str] = []
    if sort:
        order = np.argsort(t_ns, kind="stable")
        back = int(np.count_nonzero(np.diff(t_ns) < 0))
        if back:
            warnings.append(f"{path}: sorted the poses by time ({back} went back in time)")
            t_ns, positions_m, q_wxyz_raw = t_ns[order], positions_m[order], q_wxyz_raw[order]
            stamps_s = stamps_s[order] if stamps_s is not None else None
            numbers = [numbers[i] for i in order]
    keep = _check_times(path, t_ns, numbers, duplicates, warnings)
    if len(keep) != len(t_ns):
        t_ns, positions_m, q_wxyz_raw = t_ns[keep], positions_m[keep], q_wxyz_raw[keep]
        stamps_s = stamps_s[keep] if stamps_s is not None else None
        numbers = [numbers[i] for i in keep]
    q_unit = _checked_quaternions(path, q_wxyz_raw, numbers, warnings)
    if not quiet:
        for msg in warnings:
            log.warning(msg)
    positions_m = np.ascontiguousarray(positions_m)
    traj = Trajectory(t_ns=t_ns, positions_m=positions_m, q_wxyz=q_unit)
    # evo builds its matrices from the raw quaternion (rescaled by sqrt(2/n)); do the same
    poses = lie.poses_from_pq(positions_m, q_wxyz_raw)
    return PoseSource(traj, poses, str(path), str(path), fmt, True, warnings, stamps_s)


def read_tum(
    path: Path,
    duplicates: str = "error",
    *,
    sort: bool = False,
    quiet: bool = False,
    time_unit: str = "s",
) -> PoseSource:
    """TUM: ``t x y z qx qy qz qw`` (seconds, or ``time_unit``; quaternion x,y,z,w)."""
    lines, numbers, _ = _data_lines(path)
    values = _parse_table(path, lines, numbers, None, 8, "TUM")
    _check_finite(path, values, numbers)
    tokens = [ln.split(None, 1)[0] for ln in lines]
    t_ns = _times_ns(path, tokens, numbers, time_unit)
    q_wxyz = values[:, [7, 4, 5, 6]]  # TUM stores x,y,z,w -> w,x,y,z
    stamps_s = values[:, 0] / PER_SECOND[time_unit]
    return _from_pq(
        path, "tum", t_ns, values[:, 1:4], q_wxyz, numbers, duplicates, stamps_s, sort, quiet
    )


def read_euroc_csv(
    path: Path,
    duplicates: str = "error",
    *,
    sort: bool = False,
    quiet: bool = False,
    time_unit: str = "ns",
) -> PoseSource:
    """EuRoC csv: ``t_ns, px, py, pz, qw, qx, qy, qz[, v, bw, ba]`` (header may reorder q;
    ``time_unit`` for files whose first column is not in nanoseconds)."""
    lines, numbers, comments = _data_lines(path)
    header = comments[-1] if comments else ""
    if lines and lines[0][:1].isalpha():  # header without '#'
        header = lines[0]
        lines, numbers = lines[1:], numbers[1:]
        if not lines:
            raise InputError(f"{path}: empty file (no pose lines)")
    values = _parse_table(path, lines, numbers, ",", 8, "EuRoC csv", at_least=True)
    _check_finite(path, values, numbers)
    tokens = [ln.split(",", 1)[0].strip() for ln in lines]
    try:
        if time_unit != "ns":
            raise ValueError
        t_ns = np.array([int(t) for t in tokens], dtype=np.int64)
    except (ValueError, OverflowError):  # decimals, exponents, another unit or huge values
        t_ns = _times_ns(path, tokens, numbers, time_unit)
    q_cols = [4, 5, 6, 7]  # EuRoC: w,x,y,z
    names = [c.strip().lower() for c in header.lstrip("#").split(",")]
    if len(names) >= 8 and ("qw" in names[7] or names[7].endswith("_w") or names[7] == "w"):
        q_cols = [7, 4, 5, 6]  # header says x,y,z,w -> reorder to w,x,y,z
    stamps_s = values[:, 0] / PER_SECOND[time_unit]  # evo: float(ns string) / 1e9
    q_wxyz = values[:, q_cols]
    return _from_pq(
        path, "euroc", t_ns, values[:, 1:4], q_wxyz, numbers, duplicates, stamps_s, sort, quiet
    )


def read_kitti_times(path: Path, time_unit: str = "s") -> np.ndarray:
    """One time in seconds (or ``time_unit``) per line -> int64 ns."""
    lines, numbers, _ = _data_lines(path)
    tokens = []
    for line, number in zip(lines, numbers):
        parts = line.split()
        if len(parts) != 1:
            raise InputError(f"{path}:{number}: malformed times line: expected one number")
        tokens.append(parts[0])
    t_ns = _times_ns(path, tokens, numbers, time_unit)
    _check_times(path, t_ns, numbers)
    return t_ns


def read_kitti(
    path: Path, times_path: str | Path | None = None, time_unit: str = "s"
) -> PoseSource:
    """KITTI: 12 values per line, the first three rows of world_from_body."""
    lines, numbers, _ = _data_lines(path)
    values = _parse_table(path, lines, numbers, None, 12, "KITTI")
    _check_finite(path, values, numbers)
    n = len(values)
    poses = np.zeros((n, 4, 4))
    poses[:, :3, :] = values.reshape(n, 3, 4)
    poses[:, 3, 3] = 1.0
    det = np.linalg.det(poses[:, :3, :3])
    bad = np.abs(det - 1.0) > 1e-2
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path}:{numbers[i]}: rotation part is not a rotation (det {det[i]:.4g})")
    if times_path is None:
        sibling = path.with_name(path.stem + "_times.txt")
        if sibling.is_file():
            times_path = sibling
            log.info("using times file %s for %s", sibling, path)
    timed = times_path is not None
    if times_path is not None:
        t_ns = read_kitti_times(Path(times_path), time_unit)
        if len(t_ns) != n:
            raise InputError(
                f"{times_path}: {len(t_ns)} times for {n} KITTI poses in {path}; they must match"
            )
    else:
        t_ns = np.arange(n, dtype=np.int64)
    traj = Trajectory(
        t_ns=t_ns,
        positions_m=np.ascontiguousarray(poses[:, :3, 3]),
        q_wxyz=lie.matrices_to_quat_wxyz(poses[:, :3, :3]),
    )
    return PoseSource(traj, poses, str(path), str(path), "kitti", timed)


# --------------------------------------------------------------------------------------------
# bags and sequences


def _bag_reader(path: Path):  # -> rosbags AnyReader (imported lazily: ~0.2 s)
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    return AnyReader([path], default_typestore=get_typestore(Stores.LATEST))


def list_pose_topics(path: Path) -> dict[str, str]:
    """Topics of a bag with a supported pose message type: {topic: msgtype}."""
    try:
        with _bag_reader(path) as reader:
            return {
                c.topic: c.msgtype
                for c in reader.connections
                if c.msgtype in SUPPORTED_ROS_TYPES and c.msgcount > 0
            }
    except InputError:
        raise
    except Exception as exc:  # rosbags raises many reader-specific types
        raise InputError(f"{path}: cannot read as a ROS bag/MCAP ({exc})") from None


def read_bag(
    path: Path,
    topic: str | None,
    *,
    role: str = "trajectory",
    duplicates: str = "error",
    sort: bool = False,
    quiet: bool = False,
) -> PoseSource:
    """A pose topic of a ROS 1/2 bag or MCAP; header stamps, as evo."""
    topics = list_pose_topics(path)
    if topic is None:
        if GROUND_TRUTH_TOPIC in topics and role == "reference":
            topic = GROUND_TRUTH_TOPIC
        elif len(topics) == 1:
            topic = next(iter(topics))
        elif not topics:
            if role == "reference":
                return read_sequence_ground_truth(path)
            raise InputError(f"{path}: no pose topics (PoseStamped/Odometry/...) in this bag")
        else:
            flag = "--ref-topic" if role == "reference" else "--est-topic"
            raise InputError(
                f"{path}: several pose topics ({', '.join(sorted(topics))}); choose one with {flag}"
            )
    if topic not in topics:
        raise InputError(
            f"{path}: no supported pose messages on topic {topic!r} "
            f"(pose topics: {', '.join(sorted(topics)) or 'none'})"
        )
    t_list: list[int] = []
    s_list: list[float] = []
    xyz: list[tuple[float, float, float]] = []
    quat: list[tuple[float, float, float, float]] = []
    with _bag_reader(path) as reader:
        conns = [c for c in reader.connections if c.topic == topic]
        for conn, _, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp
            t_list.append(int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec))
            s_list.append(stamp.sec + stamp.nanosec * 1e-9)  # evo's float seconds
            if conn.msgtype == "geometry_msgs/msg/TransformStamped":
                p, q = msg.transform.translation, msg.transform.rotation
            else:
                pose = msg.pose
                while not hasattr(pose, "position"):  # Odometry / WithCovariance nest a pose
                    pose = pose.pose
                p, q = pose.position, pose.orientation
            xyz.append((p.x, p.y, p.z))
            quat.append((q.w, q.x, q.y, q.z))  # ROS stores x,y,z,w fields; we keep w,x,y,z
    if not t_list:
        raise InputError(f"{path}: topic {topic} has no messages")
    numbers = list(range(1, len(t_list) + 1))  # message index stands in for the line number
    values = np.column_stack([np.array(xyz, dtype=float), np.array(quat, dtype=float)])
    _check_finite(path, values, numbers)
    t_ns = np.array(t_list, dtype=np.int64)
    src = _from_pq(
        path,
        "bag",
        t_ns,
        values[:, :3],
        values[:, 3:],
        numbers,
        duplicates,
        np.array(s_list),
        sort,
        quiet,
    )
    return _renamed(src, f"{path.name}:{topic}", str(path), "bag")


def read_sequence_ground_truth(path: Path) -> PoseSource:
    """Ground truth of a sequence: EuRoC's state_groundtruth csv, else ``open_sequence``."""
    for candidate in (
        path / "mav0" / "state_groundtruth_estimate0" / "data.csv",
        path / "state_groundtruth_estimate0" / "data.csv",
    ):
        if candidate.is_file():
            return _renamed(read_euroc_csv(candidate), path.name, str(path), "sequence")
    try:
        from datasets.open import open_sequence  # type: ignore[import-not-found]
    except ImportError:
        raise InputError(
            f"{path}: no ground truth found (no mav0/state_groundtruth_estimate0/data.csv, "
            "and sequence reading is not available in this checkout)"
        ) from None
    seq = open_sequence(path)
    gt = seq.ground_truth
    if gt is None or len(gt) == 0:
        raise InputError(f"{path}: this sequence has no ground truth")
    poses = lie.poses_from_pq(gt.positions_m, gt.q_wxyz)
    return PoseSource(gt, poses, path.name, str(path), "sequence", True)


# --------------------------------------------------------------------------------------------
# writers (atomic: temp file in the same folder, then os.replace)
#
# One text format for every trajectory the project writes (``slam run`` outputs included): times
# as exact decimals of the integer nanoseconds (9 digits after the point for TUM seconds, integer
# ns for EuRoC csv), every other value as Python's shortest round-trip ``repr`` of the float64, so
# reading a written file gives back the very same numbers.

TUM_HEADER = "timestamp tx ty tz qx qy qz qw"
EUROC_HEADER = (
    "timestamp [ns],p_RS_R_x [m],p_RS_R_y [m],p_RS_R_z [m],q_RS_w [],q_RS_x [],q_RS_y [],q_RS_z []"
)


def _write_atomic(path: Path, text: str) -> None:
    from slam.core.atomic import write_atomic

    write_atomic(path, text)


def ns_to_seconds_str(t_ns: int) -> str:
    """Exact decimal seconds with 9 digits."""
    sign = "-" if t_ns < 0 else ""
    t = abs(int(t_ns))
    return f"{sign}{t // 1_000_000_000}.{t % 1_000_000_000:09d}"


def _text(comment: str, times: list[str], values: np.ndarray, sep: str) -> str:
    """The comment line, then one line per row: the time, then the values (lossless ``repr``)."""
    return "\n".join([comment, *text_rows(times, values, sep)]) + "\n"


def text_rows(times: list[str], values: np.ndarray, sep: str) -> list[str]:
    """One line per row (no newline): the time, then the values (lossless ``repr``)."""
    return [t + sep + sep.join(map(repr, v)) for t, v in zip(times, values.tolist())]


def tum_values(traj: Trajectory) -> np.ndarray:
    """The (N, 7) values of a TUM file's rows: ``x y z qx qy qz qw`` (TUM stores x,y,z,w)."""
    return np.hstack([traj.positions_m, traj.q_wxyz[:, [1, 2, 3, 0]]])


def tum_times(t_ns: np.ndarray) -> list[str]:
    """A TUM file's times: seconds, exact from the integer ns."""
    return [ns_to_seconds_str(t) for t in t_ns.tolist()]


def tum_text(traj: Trajectory, header: str = TUM_HEADER) -> str:
    """TUM text: ``t x y z qx qy qz qw``, t in seconds (exact from ns); ``header`` after a '#'."""
    return _text(f"# {header}", tum_times(traj.t_ns), tum_values(traj), " ")


def write_tum(path: str | Path, traj: Trajectory, header: str = TUM_HEADER) -> None:
    """Write :func:`tum_text` atomically."""
    _write_atomic(Path(path), tum_text(traj, header))


def euroc_csv_text(traj: Trajectory) -> str:
    """EuRoC csv in the ground-truth column names: ``t_ns,px,py,pz,qw,qx,qy,qz``."""
    return _text(f"#{EUROC_HEADER}", euroc_times(traj.t_ns), euroc_values(traj), ",")


def euroc_values(traj: Trajectory) -> np.ndarray:
    """The (N, 7) values of a EuRoC csv's rows: ``px py pz qw qx qy qz``."""
    return np.hstack([traj.positions_m, traj.q_wxyz])


def euroc_times(t_ns: np.ndarray) -> list[str]:
    """A EuRoC csv's times: integer ns."""
    return [str(t) for t in t_ns.tolist()]


def write_euroc_csv(path: str | Path, traj: Trajectory) -> None:
    """Write :func:`euroc_csv_text` atomically."""
    _write_atomic(Path(path), euroc_csv_text(traj))


def write_kitti(path: str | Path, traj: Trajectory, times_path: str | Path | None = None) -> None:
    """KITTI: 12 values per line; optionally the times (s) to a separate file."""
    poses = lie.poses_from_pq(traj.positions_m, traj.q_wxyz)
    rows = [" ".join(repr(float(v)) for v in m[:3].reshape(-1)) for m in poses]
    _write_atomic(Path(path), "\n".join(rows) + "\n")
    if times_path is not None:
        _write_atomic(
            Path(times_path), "\n".join(ns_to_seconds_str(t) for t in traj.t_ns.tolist()) + "\n"
        )
