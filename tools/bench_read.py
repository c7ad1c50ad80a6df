"""Benchmark: how fast a 60 s stereo-inertial MCAP sequence reads back.

Writes a 60 s sequence (1200 stereo 752x480 pairs at 20 Hz + 12,000 IMU samples at 200 Hz; from
the synthetic generator when it is installed, else textured random images), then times
opening + a full ``messages()`` iteration three times and reports the median as a real-time
factor (sequence seconds per wall second). Target: >= 20x.

    .venv/bin/python -m tools.bench_read [--duration 60] [--repeats 3] [--keep FILE]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from datasets.mcap_io import McapSequence, write_sequence_mcap
from datasets.memory import textured_image
from datasets.rigs import small_rig_calibration
from datasets.sequence import ImuArrays, Sequence
from slam.core.messages import StereoFrame


class TexturedSequence(Sequence):
    """Frames made on demand from a bank of textured images (no 900 MB held in memory)."""

    def __init__(self, duration_s: float, seed: int = 0) -> None:
        super().__init__(name="bench-textured", calibration=small_rig_calibration())
        rng = np.random.default_rng(seed)
        self._bank = [textured_image(rng, 752, 480) for _ in range(16)]
        start = 1_700_000_000_000_000_000
        n_frames = round(duration_s * 20)
        n_imu = round(duration_s * 200)
        self._t = start + 50_000_000 * np.arange(n_frames, dtype=np.int64)
        t_imu = start + 5_000_000 * np.arange(n_imu, dtype=np.int64)
        self._imu = ImuArrays(t_imu, rng.normal(0, 0.1, (n_imu, 3)), rng.normal(0, 0.1, (n_imu, 3)))

    def frame_times_ns(self) -> np.ndarray:
        return self._t

    def imu(self) -> ImuArrays:
        return self._imu

    def frame(self, index: int) -> StereoFrame:
        left = np.roll(self._bank[index % 16], index, axis=1)
        right = np.roll(self._bank[(index + 7) % 16], index, axis=1)
        return StereoFrame(int(self._t[index]), left, right, index)


def make_source(duration_s: float, source: str) -> tuple[Sequence, str]:
    """The synthetic generator's sequence (``synth``; ``auto`` when it is installed), else the
    textured stand-in (``textured``)."""
    if source in ("auto", "synth"):
        try:
            from datasets.synth.generator import make_synthetic_sequence

            seq = make_synthetic_sequence("figure8", duration_s=duration_s, seed=0)
            return seq, "synthetic generator (figure8, rendered while writing)"
        except ImportError:
            if source == "synth":
                raise
    return TexturedSequence(duration_s), "textured random images"


def time_read(path: Path) -> tuple[float, float, int, float]:
    """(open s, iterate s, messages, process CPU s) for one full read (wall-clock seconds)."""
    c0 = time.process_time()
    t0 = time.perf_counter()
    seq = McapSequence(path)
    t1 = time.perf_counter()
    n = 0
    checksum = 0
    for msg in seq.messages():
        n += 1
        if isinstance(msg, StereoFrame):
            checksum += int(msg.left[0, 0])
    t2 = time.perf_counter()
    seq.close()
    return t1 - t0, t2 - t1, n, time.process_time() - c0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--duration", type=float, default=60.0, help="sequence length, s")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--keep", type=Path, help="write the MCAP here and keep it")
    ap.add_argument("--read", type=Path, help="only time reading this existing MCAP file")
    ap.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd")
    ap.add_argument(
        "--source",
        choices=("auto", "synth", "textured"),
        default="auto",
        help="what to write: the synthetic generator (auto: when installed) or textured noise",
    )
    args = ap.parse_args(argv)

    if args.read:
        src: Sequence = McapSequence(args.read)
        kind, t_write = f"existing file {args.read}", float("nan")
        size_mb = args.read.stat().st_size / 1e6
        runs = [time_read(args.read) for _ in range(args.repeats)]
    else:
        src, kind = make_source(args.duration, args.source)
        with tempfile.TemporaryDirectory() as tmp:
            path = args.keep or Path(tmp) / "bench.mcap"
            t0 = time.perf_counter()
            write_sequence_mcap(src, path, progress=False, compression=args.compression)
            t_write = time.perf_counter() - t0
            size_mb = path.stat().st_size / 1e6
            runs = [time_read(path) for _ in range(args.repeats)]
    duration = src.duration_ns * 1e-9
    opens = [r[0] for r in runs]
    iters = [r[1] for r in runs]
    totals = [r[0] + r[1] for r in runs]
    med = statistics.median(totals)
    print(f"source: {kind}; {src.num_frames} stereo frames, {src.num_imu} IMU, {duration:.1f} s")
    print(f"write (incl. producing the frames): {t_write:.2f} s, file {size_mb:.0f} MB")
    print(
        f"read (open + messages(), median of {args.repeats}): {med:.2f} s "
        f"[open {statistics.median(opens):.2f} s, iterate {statistics.median(iters):.2f} s, "
        f"{runs[0][2]} messages] -> {duration / med:.1f}x real time (target >= 20x)"
    )
    cpu = statistics.median(r[3] for r in runs)
    print(
        f"CPU time of this process per read: {cpu:.2f} s -> {duration / cpu:.1f}x real time "
        "(wall and CPU differ when other work shares the cores)"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
