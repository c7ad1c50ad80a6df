"""The evaluation pipeline behind ``slam eval``: read -> associate -> align -> metric -> result.

``evaluate_ape`` / ``evaluate_rpe`` / ``evaluate_segments`` take paths and options and return
:class:`~slam.evaluation.results.EvalResult` objects plus the aligned poses (for plots).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from slam.core.errors import InputError
from slam.evaluation import align as align_mod
from slam.evaluation import metrics, timeunits
from slam.evaluation.associate import Association, associate
from slam.evaluation.io import NATIVE_TIME_UNITS, PoseSource, read_trajectory
from slam.evaluation.results import EvalResult

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvalOptions:
    """How to read, pair and align the two trajectories (the CLI flags, one to one)."""

    ref_format: str | None = None
    est_format: str | None = None
    ref_topic: str | None = None
    est_topic: str | None = None
    ref_times: str | None = None
    est_times: str | None = None
    dedupe: str = "error"  # duplicate timestamps: "error", "first", "last"
    max_diff_s: float = 0.01
    t_offset_s: float = 0.0
    interpolate: bool = False
    align: str = "se3"
    align_first: int | None = None
    ref_time_unit: str | None = None  # None: the format's own (TUM s, EuRoC csv ns)
    est_time_unit: str | None = None


@dataclass(eq=False)
class Prepared:
    """Associated and aligned poses, ready for any metric."""

    ref: PoseSource
    est: PoseSource
    association: Association
    alignment: align_mod.Alignment
    ref_poses: np.ndarray
    est_poses: np.ndarray  # aligned
    notes: list[str] = field(default_factory=list)

    @property
    def t_s(self) -> np.ndarray:
        """Seconds from the first pair (pose index when the poses have no times)."""
        t = self.association.t_ns
        if self.association.method == "index":
            return np.arange(len(t), dtype=np.float64)
        return (t - t[0]).astype(np.float64) * 1e-9

    def alignment_dict(self) -> dict:
        a = self.alignment
        return {
            "method": a.method,
            "scale": a.scale,
            "rotation": a.rotation.tolist(),
            "translation_m": a.translation_m.tolist(),
            "n_used": a.n_used,
        }

    def association_dict(self) -> dict:
        s = self.association
        return {
            "method": s.method,
            "pairs": len(s),
            "reference_poses": len(self.ref),
            "estimate_poses": len(self.est),
            "max_diff_s": s.max_diff_ns * 1e-9,
            "t_offset_s": s.t_offset_ns * 1e-9,
        }


def load_pair(
    ref_path: str | Path, est_path: str | Path, opts: EvalOptions
) -> tuple[PoseSource, PoseSource]:
    """Read reference and estimate as the options say.

    When one input's times are plainly in another unit than it was read in (nanoseconds in a
    TUM file, say), refuse with the option that fixes it (:mod:`slam.evaluation.timeunits`).
    """
    ref, ref_span, ref_err = _read_side(ref_path, "reference", opts)
    est, est_span, est_err = _read_side(est_path, "estimate", opts)
    if ref_span is not None and est_span is not None:
        message = timeunits.mismatch_message(
            ref_span,
            est_span,
            ref.name if ref is not None else str(ref_path),
            est.name if est is not None else str(est_path),
        )
        if message:
            raise InputError(message)
    if ref_err is not None:
        raise ref_err
    if est_err is not None:
        raise est_err
    assert ref is not None and est is not None
    return ref, est


def _read_side(
    path: str | Path, role: str, opts: EvalOptions
) -> tuple[PoseSource | None, timeunits.TimeSpan | None, InputError | None]:
    """One input, its time span (None if untimed), or the overflow its times caused."""
    is_ref = role == "reference"
    unit = opts.ref_time_unit if is_ref else opts.est_time_unit
    try:
        src = read_trajectory(
            path,
            opts.ref_format if is_ref else opts.est_format,
            topic=opts.ref_topic if is_ref else opts.est_topic,
            times_path=opts.ref_times if is_ref else opts.est_times,
            role=role,
            duplicates=opts.dedupe,
            time_unit=unit,
        )
    except timeunits.TimeUnitError as exc:
        return None, exc.span, exc
    if not src.timed:
        return src, None, None
    native = NATIVE_TIME_UNITS.get(src.format)
    t_ns = src.trajectory.t_ns
    span = timeunits.TimeSpan(
        float(t_ns[0]) * 1e-9,
        float(t_ns[-1]) * 1e-9,
        len(t_ns),
        unit or native or "s",
        adjustable=native is not None,
    )
    return src, span, None


def prepare(ref: PoseSource, est: PoseSource, opts: EvalOptions) -> Prepared:
    """Associate, then align the estimate to the reference."""
    assoc = associate(
        ref,
        est,
        max_diff_s=opts.max_diff_s,
        t_offset_s=opts.t_offset_s,
        interpolate=opts.interpolate,
    )
    alignment = align_mod.estimate_alignment(
        assoc.ref_poses, assoc.est_poses, opts.align, opts.align_first
    )
    est_aligned = align_mod.apply_alignment(assoc.est_poses, alignment)
    notes = [
        f"reference {ref.name} ({ref.format}, {len(ref)} poses), estimate {est.name} "
        f"({est.format}, {len(est)} poses)",
        f"association {assoc.method}: {len(assoc)} pairs"
        + (
            f" (max diff {opts.max_diff_s:g} s, offset {opts.t_offset_s:g} s)"
            if assoc.method != "index"
            else ""
        ),
        alignment.describe(),
    ]
    return Prepared(ref, est, assoc, alignment, assoc.ref_poses, est_aligned, notes)


def _align_title(p: Prepared) -> str:
    a = p.alignment
    name = {
        "se3": "SE(3) Umeyama alignment",
        "sim3": "Sim(3) Umeyama alignment",
        "scale": "scale correction",
        "posyaw": "position+yaw (4-DoF) alignment",
        "origin": "origin alignment",
        "none": "not aligned",
    }[a.method]
    text = f"({name}" if a.method != "none" else "(not aligned"
    if a.method in ("se3", "sim3", "scale", "posyaw") and a.n_used != len(p.association):
        text += f", first {a.n_used} poses"
    if a.method in ("sim3", "scale"):
        text += f", scale {a.scale:.6f}"
    return text + ")"


def ape_of(p: Prepared, relation: str = "trans") -> EvalResult:
    """APE of prepared poses."""
    errors = metrics.ape_errors(p.ref_poses, p.est_poses, relation)
    unit = metrics.RELATION_UNITS[relation]
    return EvalResult(
        kind="ape",
        title=f"APE w.r.t. {metrics.RELATION_TITLES[relation]}{f' ({unit})' if unit else ''} {_align_title(p)}",
        reference=p.ref.name,
        estimate=p.est.name,
        relation=relation,
        unit=unit,
        stats=metrics.statistics(errors),
        errors=errors,
        t_s=p.t_s,
        alignment=p.alignment_dict(),
        association=p.association_dict(),
    )


def rpe_of(
    p: Prepared,
    relation: str = "trans",
    delta: float = 1.0,
    delta_unit: str = "frames",
    all_pairs: bool = False,
    rel_tol: float = 0.1,
) -> EvalResult:
    """RPE of prepared poses for one delta."""
    pairs = metrics.rpe_pairs(
        p.est_poses, p.association.t_ns, delta, delta_unit, all_pairs=all_pairs, rel_tol=rel_tol
    )
    errors = metrics.rpe_errors(p.ref_poses, p.est_poses, pairs, relation)
    unit = metrics.RELATION_UNITS[relation]
    return EvalResult(
        kind="rpe",
        title=(
            f"RPE w.r.t. {metrics.RELATION_TITLES[relation]}{f' ({unit})' if unit else ''} for delta = "
            f"{delta:g} {delta_unit} using {'all' if all_pairs else 'consecutive'} pairs {_align_title(p)}"
        ),
        reference=p.ref.name,
        estimate=p.est.name,
        relation=relation,
        unit=unit,
        stats=metrics.statistics(errors),
        errors=errors,
        t_s=p.t_s[pairs[:, 1]],
        alignment=p.alignment_dict(),
        association=p.association_dict(),
        delta=float(delta),
        delta_unit=delta_unit,
        all_pairs=all_pairs,
        extra={"pairs": pairs.tolist()} if len(pairs) <= 100_000 else {},
    )


def resolve_lengths(spec: str, ref_poses: np.ndarray) -> tuple[float, ...]:
    """``kitti`` (100..800 m), ``rpg`` (10..50 % of the reference path) or ``a,b,c`` metres."""
    s = spec.strip().lower()
    if s == "kitti":
        return metrics.KITTI_LENGTHS_M
    if s == "rpg":
        total = float(metrics.accumulated_distances(ref_poses[:, :3, 3])[-1])
        return tuple(round(f * total, 1) for f in metrics.RPG_FRACTIONS)
    try:
        lengths = tuple(float(x) for x in s.split(",") if x)
    except ValueError:
        raise InputError(f"--lengths {spec!r}: give kitti, rpg, or metres like 10,20,40") from None
    if not lengths or min(lengths) <= 0:
        raise InputError(f"--lengths {spec!r}: lengths must be positive")
    return lengths


def segments_of(p: Prepared, lengths_m: tuple[float, ...], step: int = 10) -> list[EvalResult]:
    """Relative error over sub-trajectories of each length: drift in % and deg/m."""
    out = []
    for seg in metrics.segment_errors(p.ref_poses, p.est_poses, lengths_m, step):
        if len(seg.start_index) == 0:
            log.warning("no sub-trajectory of %.1f m (reference path too short)", seg.length_m)
            continue
        out.append(
            EvalResult(
                kind="segments",
                title=(
                    f"relative error over {seg.length_m:g} m sub-trajectories (drift % of length) "
                    f"{_align_title(p)}"
                ),
                reference=p.ref.name,
                estimate=p.est.name,
                relation="drift_pct",
                unit="%",
                stats=metrics.statistics(seg.drift_pct),
                errors=seg.drift_pct,
                t_s=p.t_s[seg.start_index],
                alignment=p.alignment_dict(),
                association=p.association_dict(),
                delta=seg.length_m,
                delta_unit="metres",
                extra={
                    "rot_deg_per_m": metrics.statistics(seg.rot_deg_per_m),
                    "trans_err_m": metrics.statistics(seg.trans_err_m),
                },
            )
        )
    if not out:
        raise InputError("no sub-trajectory fits in the reference path; use shorter --lengths")
    return out


def evaluate_ape(
    ref_path: str | Path, est_path: str | Path, opts: EvalOptions, relation: str = "trans"
) -> tuple[EvalResult, Prepared]:
    """Read, associate, align and compute the APE."""
    p = prepare(*load_pair(ref_path, est_path, opts), opts)
    return ape_of(p, relation), p
