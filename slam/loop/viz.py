"""Rerun logging of loop closures: loop edges and the corrected keyframe path."""

from __future__ import annotations

from typing import Any

import numpy as np

from slam.core.messages import LoopCorrection


def log_loop_correction(
    rec: Any,
    correction: LoopCorrection,
    keyframe_positions: dict[int, np.ndarray] | None = None,
    loop_pairs: list[tuple[int, int]] | None = None,
    entity: str = "world/loop",
) -> None:
    """Log a correction to a rerun ``RecordingStream`` (rerun 0.41).

    ``world/loop/path``: the corrected keyframe path (id order); ``world/loop/edges``: one
    segment per loop between the two keyframes' corrected positions (``loop_pairs`` as
    (query, match) ids, default: this correction's loop); ``world/loop/before``: the same
    keyframes at ``keyframe_positions`` (e.g. their odometry positions) when given. Logged at
    the stream's current time: the caller sets it (the viewer: ``correction.t_ns`` on its
    timeline).
    """
    import rerun as rr

    poses = correction.corrected_keyframe_poses
    ids = sorted(poses)
    if not ids:
        return
    path = np.array([poses[k][:3, 3] for k in ids])
    rec.log(f"{entity}/path", rr.LineStrips3D([path], colors=[40, 200, 255], radii=0.012))
    rec.log(f"{entity}/keyframes", rr.Points3D(path, colors=[40, 200, 255], radii=0.02))
    pairs = loop_pairs
    if pairs is None and correction.query_keyframe_id >= 0:
        pairs = [(correction.query_keyframe_id, correction.match_keyframe_id)]
    strips = [
        np.array([poses[q][:3, 3], poses[m][:3, 3]])
        for q, m in (pairs or [])
        if q in poses and m in poses
    ]
    if strips:
        rec.log(f"{entity}/edges", rr.LineStrips3D(strips, colors=[255, 0, 200], radii=0.02))
    if keyframe_positions:
        before = np.array([keyframe_positions[k] for k in ids if k in keyframe_positions])
        if len(before):
            rec.log(
                f"{entity}/before",
                rr.LineStrips3D([before], colors=[150, 150, 150], radii=0.006),
            )
    rec.log(
        "log",
        rr.TextLog(
            f"loop {correction.loop_id}: keyframe {correction.query_keyframe_id} -> "
            f"{correction.match_keyframe_id}, {correction.inliers} inliers, map generation "
            f"{correction.map_generation}"
        ),
    )
