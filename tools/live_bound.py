"""How good can a causal (live) pose be on a run? The bound behind issue 16's bar.

Before a run's first loop closure, a causal pose has nothing but the odometry (with what map
reuse it does): no place has been recognised yet. The best it could do from then on is the final
loop-closed pose itself, which uses the whole run (future frames included). So the ATE of the
"oracle" trajectory — the run's own live pose before its first loop closure, its loop-closed pose
from then on — is a floor for any live pose built on this odometry, however loop corrections are
passed on. Only better odometry before the first loop closure lowers it.

    python -m tools.live_bound SEQ RUN_DIR [SEQ RUN_DIR ...] [--ratio 1.5] [--out FILE.json]

For each run: the first loop closure's time (``stats.json`` events), the live, loop-closed and
oracle ATE (se3, ``tools.batch.measure.ate_se3``), the live ATE after the first loop closure, and
whether the bar ``live <= ratio x loop-closed`` is within reach (oracle <= ratio x loop-closed).
The oracle trajectory is written next to the run as ``trajectory_oracle_bound.tum``.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from slam.core.atomic import write_atomic
from slam.core.errors import InputError, SlamError
from slam.core.trajectory import Trajectory
from slam.evaluation.io import read_tum, write_tum
from tools.batch.measure import ate_se3

ORACLE_FILE = "trajectory_oracle_bound.tum"


@dataclass(frozen=True)
class LiveBound:
    """One run's live pose against what a causal pose could reach (ATE se3, metres)."""

    run: str
    first_loop_s: float | None  # since the first pose; None: the run closed no loop
    live_m: float
    loop_closed_m: float
    oracle_m: float  # live before the first loop closure, loop-closed from then on
    live_after_loop_m: float | None  # the live pose's RMSE from the first loop closure on
    ratio: float  # the bar: live <= ratio x loop-closed

    @property
    def reachable(self) -> bool:
        return self.oracle_m <= self.ratio * self.loop_closed_m


def first_loop_closure_ns(stats: dict) -> int | None:
    """Stamp of the run's first accepted loop closure (``stats.json`` events), None if none."""
    times = [
        int(e["t_ns"]) for e in stats.get("events", []) if str(e["event"]).startswith("loop closed")
    ]
    return min(times) if times else None


def oracle_trajectory(live: Trajectory, loop_closed: Trajectory, from_t_ns: int) -> Trajectory:
    """``live`` before ``from_t_ns``, ``loop_closed`` from then on, in time order."""
    before = live.t_ns < from_t_ns
    after = loop_closed.t_ns >= from_t_ns
    t_ns = np.concatenate([live.t_ns[before], loop_closed.t_ns[after]])
    order = np.argsort(t_ns, kind="stable")
    return Trajectory(
        t_ns=t_ns[order],
        positions_m=np.concatenate([live.positions_m[before], loop_closed.positions_m[after]])[
            order
        ],
        q_wxyz=np.concatenate([live.q_wxyz[before], loop_closed.q_wxyz[after]])[order],
    )


def live_bound(seq: Path, run: Path, ratio: float = 1.5) -> LiveBound:
    """The figures of one run folder (``trajectory.tum``, ``trajectory_loop_closed.tum``,
    ``stats.json``) against the ground truth of ``seq``."""
    stats_path = run / "stats.json"
    if not stats_path.is_file():
        raise InputError(f"{run}: no stats.json (not a finished `slam run` folder)")
    stats = json.loads(stats_path.read_text())
    live_path, lc_path = run / "trajectory.tum", run / "trajectory_loop_closed.tum"
    live = read_tum(live_path).trajectory
    loop_closed = read_tum(lc_path).trajectory
    live_m, lc_m = ate_se3(seq, live_path), ate_se3(seq, lc_path)
    if live_m is None or lc_m is None:
        raise InputError(f"{run}: its trajectories could not be scored against {seq}")
    t_loop = first_loop_closure_ns(stats)
    if t_loop is None:
        oracle_m, after_m, first_s = live_m, None, None
    else:
        oracle_path = run / ORACLE_FILE
        write_tum(oracle_path, oracle_trajectory(live, loop_closed, t_loop))
        oracle = ate_se3(seq, oracle_path)
        assert oracle is not None
        oracle_m = oracle
        after_m = ate_se3(seq, live_path, from_t_ns=t_loop)
        first_s = (t_loop - int(live.t_ns[0])) * 1e-9
    return LiveBound(str(run), first_s, live_m, lc_m, oracle_m, after_m, ratio)


def _row(b: LiveBound) -> str:
    first = "-" if b.first_loop_s is None else f"{b.first_loop_s:.1f} s"
    after = "-" if b.live_after_loop_m is None else f"{b.live_after_loop_m * 1e3:.2f}"
    verdict = "within reach" if b.reachable else "out of reach"
    return (
        f"| {b.run} | {first} | {b.live_m * 1e3:.2f} | {after} | {b.loop_closed_m * 1e3:.2f} | "
        f"{b.oracle_m * 1e3:.2f} | {b.ratio * b.loop_closed_m * 1e3:.2f} ({verdict}) |"
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m tools.live_bound",
        description=__doc__.split("\n\n")[0],
        epilog="ATE in mm in the table; --out writes the figures (metres) as JSON.",
    )
    ap.add_argument("pairs", nargs="+", metavar="SEQ RUN_DIR", help="sequence, then run folder")
    ap.add_argument("--ratio", type=float, default=1.5, help="the bar: live <= RATIO x loop-closed")
    ap.add_argument("--out", type=Path, help="write the figures as JSON")
    args = ap.parse_args(argv)
    if len(args.pairs) % 2:
        ap.error("give SEQ RUN_DIR pairs")
    try:
        bounds = [
            live_bound(Path(s), Path(r), args.ratio)
            for s, r in zip(args.pairs[::2], args.pairs[1::2], strict=True)
        ]
    except SlamError as e:
        print(f"live_bound: error: {e}", file=sys.stderr)
        return 2
    print("| run | first loop | live | live after it | loop-closed | oracle | bar |")
    print("|---|---|---|---|---|---|---|")
    for b in bounds:
        print(_row(b))
    if args.out:
        rows = [asdict(b) | {"reachable": b.reachable} for b in bounds]
        write_atomic(args.out, json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
