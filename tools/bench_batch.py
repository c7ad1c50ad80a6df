"""Engine overhead of `slam batch`: the same batch of short runs on the local and the Ray engine.

A batch of ``--runs`` repeats of one short synthetic sequence (stereo-vo, ``--sequential``),
one run at a time (each run declares every CPU of this machine). Per engine, the overhead per
run is (batch wall time - the sum of the `slam run` processes' wall times) / runs: starting the
task, moving the run's files back, evaluating it, writing its folder and the report (plots
included, drawn at the start and the end). The median over ``--trials`` batches is printed.

Ray is joined at ``--address`` (start a cluster first, e.g. on this machine only:
``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0 ray start --head --node-ip-address 127.0.0.1
--num-cpus 2 --include-dashboard false``); none is started here.
Results: BENCHMARKS.md (batch engines).
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path


def one_batch(seq: Path, out: Path, engine: str, address: str, runs: int) -> tuple[float, float]:
    """(batch wall s, sum of the runs' process wall s)."""
    from tools.batch.report import read_record
    from tools.batch.runner import run_batch
    from tools.batch.spec import BatchSpec, ConfigChoice, SequenceChoice

    spec = BatchSpec(
        [SequenceChoice(seq, seq.stem)],
        [ConfigChoice("stereo-vo", "stereo-vo")],
        repeats=runs,
        sequential=True,
        cpus_per_run=float(os.cpu_count() or 1),
    )
    t0 = time.perf_counter()
    result = run_batch(spec, out, engine=engine, address=address, progress=False)
    wall = time.perf_counter() - t0
    if result.failed:
        raise SystemExit(f"{result.failed} runs failed: see {out}/report.md")
    records = [read_record(out, t) for t in result.tasks]
    return wall, sum(float(r["process_wall_s"]) for r in records if r is not None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--address", default="auto", help="the Ray cluster to join")
    ap.add_argument("--runs", type=int, default=5, help="runs per batch")
    ap.add_argument("--trials", type=int, default=3, help="batches per engine")
    ap.add_argument("--duration", type=float, default=2.0, help="sequence length, s")
    ap.add_argument("--engines", default="local,ray")
    args = ap.parse_args()
    from tools.cli import main as slam

    with tempfile.TemporaryDirectory(prefix="bench-batch-") as tmp:
        seq = Path(tmp) / "short.mcap"
        slam(["synth", str(seq), "--duration", str(args.duration), "-q"])
        for engine in args.engines.split(","):
            per_run, runs_s = [], []
            for trial in range(args.trials):
                out = Path(tmp) / f"{engine}-{trial}"
                wall, run_sum = one_batch(seq, out, engine, args.address, args.runs)
                per_run.append((wall - run_sum) / args.runs)
                runs_s.append(run_sum / args.runs)
            print(
                f"{engine}: overhead per run {statistics.median(per_run):.2f} s "
                f"(trials {', '.join(f'{v:.2f}' for v in per_run)}); slam run process "
                f"{statistics.median(runs_s):.2f} s per run",
                flush=True,
            )


if __name__ == "__main__":
    main()
