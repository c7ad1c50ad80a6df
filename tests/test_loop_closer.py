"""Loop closer on synthetic keyframes with injected drift: the loop is found, verified and
corrects the trajectory; aliased places, implausible loops and false constraints do not."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from datasets.synth.keyframes import Drift, SyntheticKeyframe, ground_truth_keyframes
from slam.core.geometry import invert_transform, make_transform, rotation_angle_rad, so3_exp
from slam.core.messages import LoopCorrection
from slam.evaluation.align import ate_se3_rmse_m
from slam.loop.closer import LoopCloser, loop_closed_poses
from slam.loop.config import LoopClosureConfig
from slam.loop.vocabulary import Vocabulary, load_default_vocabulary

DRIFT = Drift(yaw_deg_per_s=0.05, translation_m_per_s=(0.003, -0.002, 0.001))


def ate_m(poses: list[np.ndarray], truth: list[np.ndarray]) -> float:
    """RMSE of positions after a rigid (SE3) alignment."""
    est = np.array([p[:3, 3] for p in poses])
    ref = np.array([p[:3, 3] for p in truth])
    return ate_se3_rmse_m(est, ref)


@pytest.fixture(scope="module")
def vocab() -> Vocabulary:
    return load_default_vocabulary()


@pytest.fixture(scope="module")
def loop_scene():
    """The ``loop`` profile (revisits its start after ~77 s), one keyframe per second."""
    from datasets.synth import make_synthetic_sequence

    seq = make_synthetic_sequence(profile="loop", seed=1)
    kfs = ground_truth_keyframes(seq, list(range(40, seq.num_frames, 20)), DRIFT)
    return seq, kfs


def run_closer(seq, kfs: list[SyntheticKeyframe], vocab, cfg=None) -> tuple[LoopCloser, list]:
    closer = LoopCloser(seq.calibration, cfg, vocabulary=vocab)
    events = []
    for s in kfs:
        ev = closer.add_keyframe(s.keyframe, s.world_from_body_odom)
        if ev is not None:
            events.append(ev)
    return closer, events


@pytest.fixture(scope="module")
def closed(loop_scene, vocab):
    seq, kfs = loop_scene
    return run_closer(seq, kfs, vocab)


def test_loop_detected_verified_and_halves_ate(loop_scene, closed) -> None:
    seq, kfs = loop_scene
    closer, events = closed
    accepted = [e for e in events if e.status == "accepted"]
    assert accepted, [(e.status, e.reason) for e in events]
    assert closer.stats.rejected_by_pgo == 0
    truth = {s.keyframe.keyframe_id: s.world_from_body_true for s in kfs}
    for rec in closer.loops:  # every accepted loop is a true revisit, its pose close to truth
        true_rel = invert_transform(truth[rec.match_kf_id]) @ truth[rec.query_kf_id]
        assert np.linalg.norm(true_rel[:3, 3] - rec.match_body_from_query_body[:3, 3]) < 0.05
        assert seq.frame_times_ns()[0] + 60e9 < rec.t_ns  # only the end of the lap revisits
    assert accepted[-1].correction is not None
    corr = accepted[-1].correction
    assert corr.map_generation >= 1
    assert set(corr.corrected_keyframe_poses) == set(range(corr.query_keyframe_id + 1))
    drifted = ate_m([s.world_from_body_odom for s in kfs], list(truth.values()))
    corrected = closer.corrected_poses()
    fixed = ate_m([corrected[s.keyframe.keyframe_id] for s in kfs], list(truth.values()))
    assert drifted > 0.05
    assert fixed <= 0.5 * drifted, (fixed, drifted)


def test_loop_closed_frame_poses_follow_keyframes(loop_scene, closed) -> None:
    _, kfs = loop_scene
    closer, _ = closed
    corr = closer.keyframe_map_from_odom()
    kt = np.array([s.keyframe.t_ns for s in kfs])
    ks = np.zeros(len(kfs), dtype=int)
    km = np.array([corr[s.keyframe.keyframe_id] for s in kfs])
    odom = np.array([s.world_from_body_odom for s in kfs])
    # frames at the keyframe times map exactly onto the corrected keyframe poses
    out = loop_closed_poses(kt, ks, odom, kt, ks, km)
    corrected = closer.corrected_poses()
    for n, s in enumerate(kfs):
        np.testing.assert_allclose(out[n], corrected[s.keyframe.keyframe_id], atol=1e-9)
    # without interpolation a frame 0.3 s after a keyframe uses that keyframe's correction
    t_later = kt[5:6] + 300_000_000
    later = loop_closed_poses(t_later, ks[:1], odom[5:6], kt, ks, km, interpolate=False)
    np.testing.assert_allclose(later[0], km[5] @ odom[5], atol=1e-9)
    # interpolated: a correction between keyframe 5's and 6's, moving its position by the same
    # fraction of the way (keyframes 1 s apart, so 30%) and rotating it part of the way
    mid = loop_closed_poses(t_later, ks[:1], odom[5:6], kt, ks, km)[0]
    alpha = 0.3e9 / (kt[6] - kt[5])
    p5, p6 = (km[5] @ odom[5])[:3, 3], (km[6] @ odom[5])[:3, 3]
    np.testing.assert_allclose(mid[:3, 3], p5 + alpha * (p6 - p5), atol=1e-4)
    r_5_mid = np.degrees(
        rotation_angle_rad((km[5][:3, :3]).T @ (mid @ invert_transform(odom[5]))[:3, :3])
    )
    r_5_6 = np.degrees(rotation_angle_rad(km[5][:3, :3].T @ km[6][:3, :3]))
    assert abs(r_5_mid - alpha * r_5_6) < 1e-6 * max(1.0, r_5_6)
    # and a frame after the last keyframe keeps the last correction
    end = loop_closed_poses(kt[-1:] + 10**9, ks[:1], odom[-1:], kt, ks, km)
    np.testing.assert_allclose(end[0], km[-1] @ odom[-1], atol=1e-9)


def test_fusion_search_links_the_same_points_across_passes(loop_scene, closed) -> None:
    """The global adjustment's fusion search matches keyframes of the revisit against the first
    lap near them (more keyframe pairs than the loops themselves); every fused landmark pair
    is the same physical point, and no pair lies within one pass."""
    _, kfs = loop_scene
    closer, _ = closed
    truth = {s.keyframe.keyframe_id: s.world_from_body_true for s in kfs}
    pairs, searched = closer._fusion_pairs(list(truth))
    assert searched == len(truth)
    kf_pairs = {(q, m) for q, _, m, _ in pairs}
    assert len(kf_pairs) > len(closer.loops) >= 1
    gap_ns = closer.cfg.global_ba_fusion_min_gap_s * 1e9
    assert all(closer.t_ns_of[q] - closer.t_ns_of[m] >= gap_ns for q, m in kf_pairs)

    def world_point(kf: int, lid: int) -> np.ndarray:
        d = closer.store.description(kf)
        p_cam = d.landmark_points_cam[np.flatnonzero(d.landmark_ids == lid)[0]]
        world_from_cam = truth[kf] @ closer.body_from_cam0
        return world_from_cam[:3, :3] @ p_cam + world_from_cam[:3, 3]

    dist = np.array([np.linalg.norm(world_point(q, a) - world_point(m, b)) for q, a, m, b in pairs])
    assert np.median(dist) < 0.01 and np.percentile(dist, 99) < 0.05, np.percentile(dist, [50, 99])


def test_implausible_loop_rejected_by_gate(loop_scene, vocab) -> None:
    """A loop implying far more drift than the odometry could have (here the drift is made
    huge) is refused: the same mechanism refuses aliased places metres apart."""
    seq, kfs = loop_scene
    big = Drift(yaw_deg_per_s=0.4, translation_m_per_s=(0.03, 0.0, 0.0))
    moved = []
    t0 = kfs[0].keyframe.t_ns
    pivot = kfs[0].world_from_body_true[:3, 3]
    for s in kfs:
        d = big.at((s.keyframe.t_ns - t0) * 1e-9, pivot) @ invert_transform(
            DRIFT.at((s.keyframe.t_ns - t0) * 1e-9, pivot)
        )
        moved.append(
            SyntheticKeyframe(s.keyframe, d @ s.world_from_body_odom, s.world_from_body_true)
        )
    closer, events = run_closer(seq, moved, vocab)
    assert closer.stats.accepted == 0
    assert closer.stats.rejected_gate >= 1
    assert any("implausible" in e.reason for e in events)


def test_false_loop_constraint_is_rejected_by_robust_pgo(loop_scene, closed, vocab) -> None:
    seq, kfs = loop_scene
    truth = {s.keyframe.keyframe_id: s.world_from_body_true for s in kfs}
    closer, _ = run_closer(seq, kfs, vocab)
    true_loops = closer.stats.accepted
    assert true_loops >= 1
    # claim keyframe 40 (far side of the ellipse) is 0.3 m from keyframe 10
    false_rel = make_transform(so3_exp(np.array([0.0, 0.2, 0.0])), [0.3, 0.0, 0.0])
    event = closer.add_loop_constraint(40, 10, false_rel)
    assert event.correction is not None
    assert closer.stats.rejected_by_pgo == 1
    assert not closer.loops[-1].active
    drifted = ate_m([s.world_from_body_odom for s in kfs], list(truth.values()))
    corrected = closer.corrected_poses()
    fixed = ate_m([corrected[k] for k in truth], list(truth.values()))
    assert fixed <= 0.5 * drifted, (fixed, drifted)


@pytest.fixture(scope="module")
def aliasing_scene():
    """Identical boxes and identical long walls; 70 s of the loop profile never revisits, but
    the far side of the ellipse looks like the start."""
    from datasets.synth import make_synthetic_sequence

    seq = make_synthetic_sequence(profile="loop", seed=1, aliasing=True, duration_s=70.0)
    return seq, ground_truth_keyframes(seq, list(range(40, seq.num_frames, 20)), DRIFT)


def test_aliasing_scene_accepts_no_loop(aliasing_scene, vocab) -> None:
    seq, kfs = aliasing_scene
    closer, events = run_closer(seq, kfs, vocab)
    assert closer.stats.accepted == 0, [(e.query_kf_id, e.match_kf_id, e.reason) for e in events]
    assert closer.loops == []
    # relaxing every gate still accepts nothing: verification itself refuses these places
    loose = LoopClosureConfig(gate_base_m=100.0, gate_base_deg=360.0)
    closer2, _ = run_closer(seq, kfs, vocab, loose)
    assert closer2.stats.accepted == 0


def test_stage_sequential_and_process_agree(loop_scene, closed, vocab) -> None:
    from slam.runtime.loop import LoopClosureStage

    seq, kfs = loop_scene
    reference, _ = closed
    results = {}
    for threaded in (False, True):
        got: list = []

        class Sink:
            def __init__(self, into: list) -> None:
                self.into = into

            def put(self, msg, block=True):
                self.into.append(msg)
                return True

        stage = LoopClosureStage(seq.calibration, LoopClosureConfig(), threaded=threaded)
        stage.connect(Sink(got), LoopCorrection)
        stage.start()
        for s in kfs:
            stage.put(s.keyframe)
        stage.close()
        stage.join()
        assert stage.error is None
        assert got, "no correction published"
        assert stage.latest.get() is got[-1]
        results[threaded] = stage.corrected_keyframe_poses()
        stats = stage.stats()
        assert stats["accepted"] == reference.stats.accepted
        assert stats["mode"] == ("process" if threaded else "inline")
    ref = reference.corrected_poses()
    for k, pose in ref.items():
        np.testing.assert_allclose(results[False][k], pose, atol=1e-9)
        np.testing.assert_allclose(results[True][k][:3, 3], pose[:3, 3], atol=1e-3)


def test_log_loop_correction_writes_rerun(closed, tmp_path) -> None:
    import rerun as rr

    from slam.loop.viz import log_loop_correction

    closer, events = closed
    correction = next(e.correction for e in events if e.correction is not None)
    rec = rr.RecordingStream("test-loop")
    path = tmp_path / "loop.rrd"
    rec.save(str(path))
    log_loop_correction(rec, correction, {k: p[:3, 3] for k, p in closer.odom.items()})
    rec.flush()
    rec.disconnect()
    assert path.stat().st_size > 1000


def test_second_segment_is_merged_by_two_agreeing_loops(loop_scene, vocab) -> None:
    """Keyframes 40+ form segment 1 whose odometry frame is offset by 1 m / 29 deg (as after
    an unrecovered tracking loss); the revisit links it to segment 0 once a second loop agrees."""
    import dataclasses

    seq, kfs = loop_scene
    off = make_transform(so3_exp(np.array([0.0, 0.0, 0.5])), [1.0, -2.0, 0.3])
    split = []
    for s in kfs:
        k = s.keyframe
        if k.keyframe_id >= 40:
            k = dataclasses.replace(
                k,
                segment_id=1,
                world_from_body_vo=off @ k.world_from_body_vo,
                points_world_vo=k.points_world_vo @ off[:3, :3].T + off[:3, 3],
            )
            s = SyntheticKeyframe(k, off @ s.world_from_body_odom, s.world_from_body_true)
        split.append(s)
    closer, events = run_closer(seq, split, vocab)
    assert [e.status for e in events if e.status != "rejected"][:2] == ["pending", "accepted"]
    assert closer.stats.accepted == 2
    assert closer._root(1) == closer._root(0)
    truth = [s.world_from_body_true for s in split]
    corrected = closer.corrected_poses()
    before = ate_m([s.world_from_body_odom for s in split], truth)
    after = ate_m([corrected[s.keyframe.keyframe_id] for s in split], truth)
    assert before > 0.5 and after < 0.25, (before, after)
    last = closer.last_correction
    assert last is not None and set(last.map_from_odom) == {0, 1}


def test_fusion_search_stops_at_its_deadline(loop_scene, closed) -> None:
    """A spent deadline searches nothing; the search visits keyframes spread over the run
    (every 8th first), so a cut search still covers the whole map."""
    import time

    _, kfs = loop_scene
    closer, _ = closed
    ids = [s.keyframe.keyframe_id for s in kfs]
    pairs, searched = closer._fusion_pairs(ids, deadline=time.perf_counter() - 1.0)
    assert (pairs, searched) == ([], 0)
    full, searched = closer._fusion_pairs(ids, deadline=time.perf_counter() + 600.0)
    assert searched == len(ids) and len(full) > 0


def test_backlog_that_used_the_budget_skips_the_adjustment() -> None:
    """The end of a run behind on a busy machine: when draining the loop backlog already took
    most of the global adjustment's budget, the adjustment is skipped and the summary says
    why; with enough of it left it is not skipped for that reason."""
    import time

    from datasets.rigs import euroc_like_calibration
    from slam.runtime.loop import LoopCore

    core = LoopCore(euroc_like_calibration(), LoopClosureConfig(global_ba_budget_fraction=0.1))
    core.closer.t_ns_of.update({0: 0, 1: 20_000_000_000})  # keyframes 20 s apart: 2 s budget
    assert core.closer.global_adjustment_budget_s() == pytest.approx(2.0)
    for spent_s in (3.0, 1.5):  # all of it; less than global_ba_min_budget_share (0.4) left
        core.end_began_s = time.perf_counter() - spent_s
        final = core.finish(interrupted=False)
        assert final.stats["global_ba_skipped"].startswith("the loop backlog used its time budget")
        assert final.stats["global_ba"] is None
    core.end_began_s = time.perf_counter() - 0.5
    assert core.finish(interrupted=False).stats["global_ba_skipped"] is None


def test_rigid_fit_recovers_a_gauge_change() -> None:
    """``pgo_align_to_odometry``: a pose-graph result moved rigidly away from the odometry is
    moved back exactly."""
    from slam.loop.closer import _rigid_fit

    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 3, (40, 3))
    gauge = make_transform(so3_exp(np.array([0.01, -0.02, 0.3])), [0.1, -0.2, 0.05])
    moved = pts @ gauge[:3, :3].T + gauge[:3, 3]
    back = _rigid_fit(moved, pts)
    assert np.allclose(back @ gauge, np.eye(4), atol=1e-9)


def test_covisibility_edge_fits_the_relative_pose_of_a_map_reuse(loop_scene, vocab) -> None:
    """A keyframe that re-observes an older keyframe's landmarks (map reuse) gets a pose-graph
    edge to it, fitted on patches from the odometry's relative pose: its error against the
    truth is far below the odometry's."""
    import dataclasses

    seq, _ = loop_scene
    kfs = ground_truth_keyframes(seq, [40, 50, 60])
    first, last = kfs[0].keyframe, kfs[2].keyframe
    ids = last.landmark_ids.copy()
    ids[:20] = first.landmark_ids[:20]  # the front end found 20 of them again
    error = make_transform(so3_exp(np.radians([0.1, -0.1, 0.05])), [0.005, -0.003, 0.002])
    pts = last.points_world_vo @ error[:3, :3].T + error[:3, 3]
    moved = dataclasses.replace(
        last,
        landmark_ids=ids,
        world_from_body_vo=error @ last.world_from_body_vo,
        points_world_vo=pts,
    )
    cfg = LoopClosureConfig(covisibility_min_gap_s=0.0, covisibility_edges="found")
    closer = LoopCloser(seq.calibration, cfg, vocabulary=vocab)
    closer.add_keyframe(first, kfs[0].world_from_body_odom)
    closer.add_keyframe(kfs[1].keyframe, kfs[1].world_from_body_odom)
    closer.add_keyframe(moved, moved.world_from_body_vo)
    assert closer.stats.covisibility_edges == 1
    edge = closer.covisibility_edges[0]
    assert (edge.from_id, edge.to_id) == (0, 2)
    true_rel = invert_transform(kfs[0].world_from_body_true) @ kfs[2].world_from_body_true
    odom_rel = invert_transform(closer.odom[0]) @ closer.odom[2]
    err_odom = np.linalg.norm(odom_rel[:3, 3] - true_rel[:3, 3])
    err_edge = np.linalg.norm(edge.from_node_from_to_node[:3, 3] - true_rel[:3, 3])
    assert err_odom > 0.005
    assert err_edge < 0.3 * err_odom, (err_edge, err_odom)
    rot_err = rotation_angle_rad(edge.from_node_from_to_node[:3, :3].T @ true_rel[:3, :3])
    assert np.degrees(rot_err) < 0.05
    # the pose graph carries it (not as a loop)
    closer.add_loop_constraint(2, 0, true_rel)
    req = closer.pgo_request()
    assert any((e.from_id, e.to_id) == (0, 2) for e in req.odometry_edges)


def test_adjustment_offers_the_pose_graph_result_as_a_fallback_first() -> None:
    """In a worker process the loop core sends its state without the global adjustment before
    the adjustment starts, to be used from the budget's end plus ``global_ba_grace_s``; the
    fallback's summary says the adjustment was stopped. None is offered when the adjustment
    is skipped anyway or has no budget."""
    import time

    from datasets.rigs import euroc_like_calibration
    from slam.runtime.loop import LoopCore

    cfg = LoopClosureConfig(global_ba_budget_fraction=0.1, global_ba_grace_s=0.7)
    core = LoopCore(euroc_like_calibration(), cfg)
    core.closer.t_ns_of.update({0: 0, 1: 20_000_000_000})  # 2 s budget
    offered: list[tuple[Any, float]] = []
    core.offer_fallback = lambda payload, use_after_s: offered.append((payload, use_after_s))
    began_s = time.perf_counter() - 0.5
    core.end_began_s = began_s
    final = core.finish(interrupted=False)
    assert final.stats["global_ba_skipped"] is None
    ((fallback, use_after_s),) = offered
    assert use_after_s == pytest.approx(began_s + 2.0 + 0.7, abs=1e-3)
    assert fallback.stats["global_ba_skipped"].startswith("stopped: not done within its time")
    assert fallback.stats["global_ba"] is None
    offered.clear()
    core.end_began_s = time.perf_counter() - 3.0  # the backlog used the budget: skipped
    core.finish(interrupted=False)
    core.finish(interrupted=True)
    assert offered == []
