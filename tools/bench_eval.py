"""Benchmark: `slam eval ape` vs `evo_ape` as whole processes on 10,000-pose TUM pairs.

Same work for both: read two TUM files, associate (nearest, 10 ms), SE(3) Umeyama alignment,
APE (translation). Runs each command several times, alternating, and prints the medians, the
ratio, and whether the two RMSEs agree.

    .venv/bin/python -m tools.bench_eval [--poses 10000] [--repeats 7]
"""

from __future__ import annotations

import argparse
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_pair(folder: Path, n: int, seed: int = 0) -> tuple[Path, Path]:
    """A smooth 3D reference at 100 Hz and a noisy, rotated, offset estimate at the same times."""
    rng = np.random.default_rng(seed)
    t = 1_403_715_273.0 + np.arange(n) * 0.01
    s = np.arange(n) * 0.01
    pos = np.column_stack([3 * np.cos(0.2 * s), 2 * np.sin(0.3 * s), 0.5 * np.sin(0.1 * s)])
    yaw = 0.2 * s
    q_xyzw = np.column_stack([np.zeros(n), np.zeros(n), np.sin(yaw / 2), np.cos(yaw / 2)])
    est_pos = pos @ np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]).T + 1.0
    est_pos += rng.normal(scale=0.02, size=est_pos.shape)
    t_est = t + rng.uniform(-0.002, 0.002, size=n)
    ref_path, est_path = folder / "ref.txt", folder / "est.txt"
    np.savetxt(ref_path, np.column_stack([t, pos, q_xyzw]), fmt="%.9f")
    np.savetxt(est_path, np.column_stack([t_est, est_pos, q_xyzw]), fmt="%.9f")
    return ref_path, est_path


def time_command(cmd: list[str]) -> tuple[float, str]:
    start = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed:\n{proc.stderr}")
    return elapsed, proc.stdout + proc.stderr


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--poses", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args(argv)
    bindir = Path(sys.executable).parent
    slam, evo = str(bindir / "slam"), str(bindir / "evo_ape")
    if not Path(evo).exists():
        raise SystemExit(f"evo_ape not found next to {sys.executable} (pip install evo==1.38.*)")
    with tempfile.TemporaryDirectory() as tmp:
        ref, est = make_pair(Path(tmp), args.poses)
        args_ape = ["ape", str(ref), str(est), "--align", "se3", "--max-diff", "0.01"]
        ours_cmd = [slam, "eval", *args_ape]
        # the eval module alone: what `slam eval` costs without the other command modules'
        # top-level imports (tools/cli.py imports every cmd_* module at start-up)
        alone_cmd = [sys.executable, "-m", "tools.cmd_eval", *args_ape]
        evo_cmd = [
            evo,
            "tum",
            str(ref),
            str(est),
            "--align",
            "--t_max_diff",
            "0.01",
            "--no_warnings",
        ]
        time_command(ours_cmd)  # warm the file cache and .pyc files
        _, evo_out = time_command(evo_cmd)
        time_command(alone_cmd)
        t_ours, t_alone, t_evo = [], [], []
        ours_out = ""
        for _ in range(args.repeats):
            dt, ours_out = time_command(ours_cmd)
            t_ours.append(dt)
            dt, _ = time_command(alone_cmd)
            t_alone.append(dt)
            dt, evo_out = time_command(evo_cmd)
            t_evo.append(dt)
    rmse_ours = float(re.search(r"rmse\s+([0-9.eE+-]+)", ours_out).group(1))  # type: ignore[union-attr]
    rmse_evo = float(re.search(r"rmse\s+([0-9.eE+-]+)", evo_out).group(1))  # type: ignore[union-attr]
    m_ours, m_evo = statistics.median(t_ours), statistics.median(t_evo)
    m_alone = statistics.median(t_alone)
    print(
        f"{args.poses} poses per trajectory, {args.repeats} runs each (whole processes, alternating)"
    )
    print(
        f"slam eval ape: median {m_ours * 1e3:7.1f} ms   (runs: {', '.join(f'{t * 1e3:.0f}' for t in t_ours)})"
    )
    print(
        f"python -m tools.cmd_eval ape: median {m_alone * 1e3:7.1f} ms   (runs: {', '.join(f'{t * 1e3:.0f}' for t in t_alone)})"
    )
    print(
        f"evo_ape:       median {m_evo * 1e3:7.1f} ms   (runs: {', '.join(f'{t * 1e3:.0f}' for t in t_evo)})"
    )
    print(f"ratio slam eval / evo_ape: {m_ours / m_evo:.3f}  (target <= 0.333)")
    print(f"ratio eval module alone / evo_ape: {m_alone / m_evo:.3f}")
    print(f"rmse: slam {rmse_ours:.6g}, evo {rmse_evo:.6g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
