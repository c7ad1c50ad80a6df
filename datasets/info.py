"""Human-readable summaries of sequences and MCAP files (what ``slam info`` prints)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from datasets.mcap_scan import ScanResult, scan_mcap
from datasets.open import find_mcap, open_sequence
from datasets.sequence import Sequence
from datasets.timing import find_gaps, rate_hz
from slam.core.errors import InputError


def _span(t_ns: np.ndarray) -> str:
    if len(t_ns) == 0:
        return "none"
    return f"{t_ns[0] * 1e-9:.3f} .. {t_ns[-1] * 1e-9:.3f} s ({(t_ns[-1] - t_ns[0]) * 1e-9:.2f} s)"


def topic_lines(scan: ScanResult) -> list[str]:
    """One line per topic: type, count, rate and span (from log times)."""
    lines = [
        f"MCAP {scan.path}: profile {scan.profile or '(none)'}, {scan.file_size / 1e6:.1f} MB, "
        f"{len(scan.chunks)} chunks, metadata: {', '.join(scan.metadata) or 'none'}"
    ]
    width = max((len(t) for t in scan.topics()), default=5)
    for topic, (schema, count) in scan.topics().items():
        ids = scan.channel_ids(topic)
        t = np.sort(scan.msg_log_ns[np.isin(scan.msg_channel, ids)])
        enc = ",".join(sorted({scan.channels[c].message_encoding for c in ids}))
        lines.append(
            f"  {topic:<{width}}  {schema:<40} {enc:<5} {count:7d} msgs  "
            f"{rate_hz(t):8.2f} Hz  {_span(t)}"
        )
    return lines


def overlap_line(frame_t_ns: np.ndarray, imu_t_ns: np.ndarray) -> str:
    """What a run uses: every frame, with IMU where the two streams overlap (IMU samples are
    handed on with the next frame, so those after the last frame are never used)."""
    ft, it = frame_t_ns, imu_t_ns
    if len(ft) == 0:
        return "  overlap  none: no frames, a run has nothing to track"
    if len(it) == 0:
        return f"  overlap  none: no IMU, a run uses the frames alone, {_span(ft)}"
    lo, hi = max(int(ft[0]), int(it[0])), min(int(ft[-1]), int(it[-1]))
    if hi < lo:
        return f"  overlap  none: the IMU misses the frames, a run uses them alone, {_span(ft)}"
    notes = []
    bare = int(np.count_nonzero((ft < lo) | (ft > hi)))
    if bare:
        notes.append(f"{bare} frames outside it have no IMU")
    unused = max(0, int(ft[0]) - int(it[0])) + max(0, int(it[-1]) - int(ft[-1]))
    if unused:
        notes.append(f"{unused * 1e-9:.2f} s of IMU outside the frames are not used")
    both = _span(np.array([lo, hi], dtype=np.int64))
    return f"  overlap  {both} of frames and IMU: what a run uses" + (
        f" ({'; '.join(notes)})" if notes else ""
    )


def sequence_lines(seq: Sequence) -> list[str]:
    """Counts, spans, rates, gaps, calibration and ground truth of an opened sequence (after
    :meth:`verify` where the source has one: what a run will get)."""
    ft = seq.frame_times_ns()
    imu = seq.imu()
    cal = seq.calibration
    lines = [
        f"sequence {seq.name!r} ({type(seq).__name__})",
        f"  frames   {len(ft):7d} {'stereo' if cal.is_stereo else 'mono'}  "
        f"{rate_hz(ft):7.2f} Hz  {_span(ft)}",
        f"  imu      {len(imu):7d}         {rate_hz(imu.t_ns):7.2f} Hz  {_span(imu.t_ns)}",
        overlap_line(ft, imu.t_ns),
    ]
    for what, t in (("frames", ft), ("imu", imu.t_ns)):
        note = find_gaps(t).describe(what)
        lines.append(f"  gaps     {note}" if note else f"  gaps     {what}: none")
    lines.append("calibration:")
    for cam in cal.cameras:
        i = cam.intrinsics
        dist = ", ".join(f"{d:.6g}" for d in i.distortion)
        lines.append(
            f"  {cam.name}: {i.width}x{i.height} fx {i.fx:.3f} fy {i.fy:.3f} cx {i.cx:.3f} "
            f"cy {i.cy:.3f} {i.distortion_model} [{dist}]; body_from_cam t = "
            f"{np.array2string(cam.body_from_cam[:3, 3], precision=4)} m"
        )
    if cal.is_stereo:
        lines.append(f"  stereo baseline {cal.stereo_baseline_m() * 100:.2f} cm")
    if cal.imu is not None:
        m = cal.imu
        lines.append(
            f"  imu: {m.rate_hz:g} Hz, gyro noise {m.gyro_noise_density:.3e} rad/s/sqrt(Hz), "
            f"gyro walk {m.gyro_random_walk:.3e}, accel noise {m.accel_noise_density:.3e} "
            f"m/s^2/sqrt(Hz), accel walk {m.accel_random_walk:.3e}"
        )
    lines.append(f"  time offset (t_imu = t_cam + offset): {cal.time_offset_ns * 1e-6:.3f} ms")
    exposure = seq.exposures_ns()
    if exposure is not None and np.any(exposure > 0):
        e_ms = exposure[exposure > 0] * 1e-6
        lines.append(
            f"  exposure recorded for {len(e_ms)}/{len(ft)} frames: {e_ms.min():.2f} / "
            f"{np.median(e_ms):.2f} / {e_ms.max():.2f} ms min / median / max (a run stamps "
            "each image at its middle: player.mid_exposure)"
        )
    gt = seq.ground_truth
    if gt is None or len(gt) == 0:
        lines.extend(ground_truth_hint(seq))
    else:
        lines.append(
            f"ground truth: {len(gt)} poses, {rate_hz(gt.t_ns):.1f} Hz, {_span(gt.t_ns)}, "
            f"path {gt.path_length_m():.2f} m, covers {_covered(gt.t_ns, ft)} frames"
        )
    if seq.warnings:
        lines.append(f"warnings ({len(seq.warnings)}):")
        lines.extend(f"  - {w}" for w in seq.warnings)
    else:
        lines.append("warnings: none")
    return lines


def _covered(gt_t_ns: np.ndarray, ft: np.ndarray) -> str:
    n = np.count_nonzero((ft >= gt_t_ns[0]) & (ft <= gt_t_ns[-1])) if len(gt_t_ns) else 0
    return f"{n}/{len(ft)}"


def ground_truth_hint(seq: Sequence) -> list[str]:
    """For a sequence without ground truth: the trajectory files in its folder, or how to
    pass one."""
    root = getattr(seq, "root", None)  # an ASL folder's mav0
    found = []
    if isinstance(root, Path):
        dataset = root.parent if root.name == "mav0" else root
        found = ground_truth_files(dataset)
    how = "pass one with --gt FILE (EuRoC csv or TUM text)"
    if not found:
        return [f"ground truth: none; {how}"]
    from datasets.euroc import read_trajectory_file

    ft = seq.frame_times_ns()
    lines = [
        "ground truth: none in the sequence; trajectory files in its folder (pass one with "
        "--gt FILE):"
    ]
    for path in found:
        try:
            traj = read_trajectory_file(path)
        except InputError:
            continue
        lines.append(
            f"  {path}: {len(traj)} poses, {rate_hz(traj.t_ns):.1f} Hz, covers "
            f"{_covered(traj.t_ns, ft)} frames"
        )
    return lines if len(lines) > 1 else [f"ground truth: none; {how}"]


SENSOR_PREFIXES = ("cam", "imu", "leica")  # ASL sensor folders (and their data/): not ground truth


def _sensor_folder(name: str) -> bool:
    return name.lower().startswith(SENSOR_PREFIXES) or name == "data"


def ground_truth_files(root: Path, max_depth: int = 2) -> list[Path]:
    """Files under ``root`` (at most ``max_depth`` folders down, sensor folders skipped) that
    look like trajectories (TUM text or EuRoC csv), sorted."""
    from slam.evaluation.io import detect_format

    found: list[Path] = []
    for folder, dirs, files in os.walk(root):
        depth = len(Path(folder).relative_to(root).parts)
        dirs[:] = sorted(d for d in dirs if depth < max_depth and not _sensor_folder(d))
        for name in sorted(files):
            p = Path(folder) / name
            if p.suffix.lower() not in (".csv", ".txt", ".tum"):
                continue
            try:
                if detect_format(p) in ("tum", "euroc"):
                    found.append(p)
            except (InputError, OSError):
                continue
    return found


def describe(path: str | os.PathLike[str], **open_kwargs: object) -> tuple[list[str], bool]:
    """Summary lines of ``path`` and whether it opened as a sequence.

    An MCAP file that is not a usable sequence (no camera topic, no calibration) still gets its
    topic list, followed by the reason it cannot be used.
    """
    lines: list[str] = []
    try:
        seq = open_sequence(path, **open_kwargs)  # type: ignore[arg-type]
    except InputError as exc:
        mcap = find_mcap(path) if Path(path).exists() else None
        if mcap is None:
            raise
        found = scan_mcap(mcap)
        lines.extend(topic_lines(found))
        notes = [*found.warnings, found.truncation_note()]
        lines.extend(f"warning: {w}" for w in notes if w)
        lines.append(f"not usable as a sequence: {exc}")
        return lines, False
    verify = getattr(seq, "verify", None)
    if callable(verify):  # CRC-check chunks opening did not read; drops the frames a run skips
        verify()
    scan = getattr(seq, "scan", None)
    if isinstance(scan, ScanResult):
        lines.extend(topic_lines(scan))
    lines.extend(sequence_lines(seq))
    return lines, True
