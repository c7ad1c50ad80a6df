"""Global bundle adjustment after loop closure: on a synthetic stereo loop with drifted
odometry, fusing the landmarks a loop matched removes the drift; without the fusion it cannot;
long tracks are split."""

from __future__ import annotations

import numpy as np
import pytest
from stereo_observations import observe

from datasets.rigs import euroc_like_calibration
from slam.core.geometry import invert_transform, make_transform, so3_exp
from slam.evaluation.align import ate_se3_rmse_m
from slam.loop.closer import odometry_sigmas
from slam.loop.config import LoopClosureConfig
from slam.loop.global_ba import (
    GlobalBaParams,
    GlobalBaResult,
    KeyframeObservations,
    _fuse,
    _keyframe_sigma_factors,
    _outlier_limit,
    _spread_rows,
    _thinned,
    global_bundle_adjustment,
)
from slam.posegraph import PoseEdge, information_from_sigmas

NUM_KF = 48
KF_DT_NS = 500_000_000
TRACK_KF = 3  # the simulated front end re-detects a point every 3 keyframes (new id)


@pytest.fixture(scope="module")
def loop_world():
    """A camera rig on a 1 m circle looking outwards at points on a 4 m cylinder, one lap in
    48 keyframes plus a revisit of the start; odometry drifts by yaw and translation."""
    rng = np.random.default_rng(3)
    calib = euroc_like_calibration()
    cams = calib.cameras[:2]
    angles = np.linspace(0, 2 * np.pi, NUM_KF, endpoint=False)
    angles = np.concatenate([angles, angles[:4] + 2 * np.pi])  # revisit the first 4 places
    # body x up, z forward (EuRoC-like): forward = outward radial direction
    true = []
    for a in angles:
        fwd = np.array([np.cos(a), np.sin(a), 0.0])
        up = np.array([0.0, 0.0, 1.0])
        rot = np.column_stack([up, np.cross(fwd, up), fwd])
        true.append(make_transform(rot, 1.0 * fwd))
    true_arr = np.array(true)
    phi = rng.uniform(0, 2 * np.pi, 3000)
    pts = np.column_stack([4.0 * np.cos(phi), 4.0 * np.sin(phi), rng.uniform(-1.5, 1.5, 3000)])
    t_ns = {k: k * KF_DT_NS for k in range(len(true))}
    obs: dict[int, KeyframeObservations] = {}
    for k, pose in enumerate(true):
        j, uv_left, uv_right, p_cam0 = observe(pose, cams, pts, 0.2, rng)
        track = k % NUM_KF // TRACK_KF  # after the lap, the same place gets new ids
        obs[k] = KeyframeObservations(
            (j * 1000 + track + (500 if k >= NUM_KF else 0)).astype(np.int64),
            uv_left,
            uv_right,
            p_cam0,
        )
    # drifted odometry: yaw 0.03 deg and 3 mm per keyframe step accumulate
    odom = []
    for k, pose in enumerate(true):
        d = make_transform(so3_exp(np.array([0, 0, np.radians(0.03 * k)])), [0.003 * k, 0, 0])
        odom.append(d @ pose)
    cfg = LoopClosureConfig()
    edges = []
    for k in range(1, len(true)):
        rel = invert_transform(odom[k - 1]) @ odom[k]
        s_m, s_rad = odometry_sigmas(rel, KF_DT_NS * 1e-9, cfg)
        edges.append(PoseEdge(k - 1, k, rel, information_from_sigmas(s_m, s_rad)))
    # the loop: the revisit keyframes' landmarks are the first keyframes' (ids known here)
    pairs = []
    for q in range(NUM_KF, len(true)):
        m = q - NUM_KF
        by_point_m = {int(i) // 1000: int(i) for i in obs[m].landmark_ids}
        for i in obs[q].landmark_ids.tolist():
            j = int(i) // 1000
            if j in by_point_m:
                pairs.append((q, int(i), m, by_point_m[j]))
    return calib, obs, true_arr, np.array(odom), edges, pairs, t_ns


def test_fusing_loop_landmarks_removes_drift(loop_world) -> None:
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    poses = {k: odom[k] for k in range(len(odom))}
    before = ate_se3_rmse_m(odom[:, :3, 3], true[:, :3, 3])
    res = global_bundle_adjustment(calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams())
    assert res is not None
    after = ate_se3_rmse_m(np.array([res.world_from_body[k][:3, 3] for k in poses]), true[:, :3, 3])
    assert before > 0.03
    assert after < 0.01, (before, after, res.summary())
    assert res.fused_landmarks > 50
    assert res.rms_px_after < 0.5  # noise 0.2 px per axis
    # Without the loop's landmark pairs nothing ties the end to the start: drift stays.
    assert global_bundle_adjustment(calib, obs, poses, edges, [], 0, t_ns) is None  # the
    # last keyframe's only landmarks are its own: too few observations to adjust it safely
    free = global_bundle_adjustment(
        calib, obs, poses, edges, [], 0, t_ns, GlobalBaParams(min_observations=0)
    )
    assert free is not None
    free_ate = ate_se3_rmse_m(
        np.array([free.world_from_body[k][:3, 3] for k in poses]), true[:, :3, 3]
    )
    assert free_ate > 5 * after, (free_ate, after)


def test_long_tracks_are_split(loop_world) -> None:
    calib, obs, _, odom, edges, _, t_ns = loop_world
    poses = {k: odom[k] for k in range(12)}
    sub = {k: obs[k] for k in poses}
    whole = global_bundle_adjustment(
        calib, sub, poses, edges, [], 0, t_ns, GlobalBaParams(max_track_s=10.0, max_iterations=1)
    )
    split = global_bundle_adjustment(
        calib, sub, poses, edges, [], 0, t_ns, GlobalBaParams(max_track_s=0.6, max_iterations=1)
    )
    assert whole is not None and split is not None
    # 3-keyframe tracks at 0.5 s spacing span 1 s: split at 0.6 s, each track's third
    # observation is alone and falls below min_keyframes: about a third of the observations go
    assert split.landmarks == whole.landmarks
    assert 0.6 < split.observations / whole.observations < 0.8


def test_fuse_is_transitive() -> None:
    ids = np.array([1, 2, 3, 4, 5, 9])
    out = _fuse(ids, [(5, 3), (3, 9), (2, 1)])
    assert out.tolist() == [1, 1, 3, 4, 3, 3]


def test_time_budget_keeps_the_estimate_so_far(loop_world) -> None:
    """A spent budget stops after one iteration and skips the outlier round; the estimate is
    still an improvement. A generous budget gives the unbounded result."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    poses = {k: odom[k] for k in range(len(odom))}

    def ate(res) -> float:  # type: ignore[no-untyped-def]
        return ate_se3_rmse_m(
            np.array([res.world_from_body[k][:3, 3] for k in poses]), true[:, :3, 3]
        )

    free = global_bundle_adjustment(calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams())
    spent = global_bundle_adjustment(
        calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams(time_budget_s=0.0)
    )
    ample = global_bundle_adjustment(
        calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams(time_budget_s=600.0)
    )
    assert free is not None and spent is not None and ample is not None
    assert spent.time_boxed and spent.iterations == 1
    assert not free.time_boxed and not ample.time_boxed and free.iterations > 1
    assert spent.rms_px_after < spent.rms_px_before
    assert ate(spent) < ate_se3_rmse_m(odom[:, :3, 3], true[:, :3, 3])
    assert abs(ate(ample) - ate(free)) < 1e-4


def test_spread_rows_keeps_first_last_and_spreads() -> None:
    group = np.array([7] * 20 + [3] * 3 + [5])
    t = np.concatenate([np.arange(20)[::-1], [2, 0, 1], [4]])  # not in time order
    kept = _spread_rows(group, t, 5)
    assert np.all(np.diff(kept) > 0)  # original order
    by_group = {g: sorted(t[kept][group[kept] == g].tolist()) for g in (7, 3, 5)}
    assert by_group[3] == [0, 1, 2] and by_group[5] == [4]  # small groups whole
    seven = by_group[7]
    assert seven[0] == 0 and seven[-1] == 19 and 5 <= len(seven) <= 6
    assert max(np.diff(seven)) <= 5  # evenly spread, no long hole


def test_thinned_observations_keep_the_result(loop_world) -> None:
    """Each landmark kept in at most 2 of its 3 keyframes: a third fewer observations, the
    drift still removed."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    poses = {k: odom[k] for k in range(len(odom))}
    full = global_bundle_adjustment(calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams())
    thin = global_bundle_adjustment(
        calib, obs, poses, edges, pairs, 0, t_ns, GlobalBaParams(max_keyframes_per_landmark=2)
    )
    assert full is not None and thin is not None
    assert thin.observations < 0.85 * full.observations
    after = ate_se3_rmse_m(
        np.array([thin.world_from_body[k][:3, 3] for k in poses]), true[:, :3, 3]
    )
    assert after < 0.01


def test_thinning_by_track_keeps_each_pass_share() -> None:
    """One fused landmark: 12 keyframes of a first pass (track 1), 3 of a revisit (track 2),
    each keyframe with 2 other landmarks seen once. Counted per fused landmark, 4 kept leave
    the revisit 1 observation; per track it keeps all 3 (and the first pass 4)."""
    kf = np.concatenate([np.arange(15), np.repeat(np.arange(15), 2)])
    t = kf * 100
    others = np.arange(100, 130)
    track = np.concatenate([[1] * 12 + [2] * 3, others])
    fused = np.concatenate([np.zeros(15, np.int64), others])
    by_landmark = _thinned(fused, t, kf, 4, 1)
    by_track = _thinned(track, t, kf, 4, 1)
    assert by_landmark[12:15].sum() == 1 and by_landmark[:15].sum() == 4
    assert by_track[12:15].all() and by_track[:12].sum() == 4
    assert by_landmark[15:].all() and by_track[15:].all()
    # a keyframe left short of 2 x min_observations keeps all of its own rows
    assert _thinned(fused, t, kf, 4, 2).all()


def test_shared_limit_spreads_a_fused_landmark_over_its_tracks() -> None:
    """One fused landmark over 20 tracks of 10 keyframes each (a small room's passes), each
    keyframe with 2 other landmarks: per track alone it keeps all 200 rows; with 40 shared
    (``max_observations_per_landmark``: 40 // 20 = 2 per track) each track keeps its first and
    last keyframe, 40 in all; the other landmarks keep theirs."""
    n = 200
    kf = np.concatenate([np.arange(n), np.repeat(np.arange(n), 2)])
    t = kf * 100
    others = np.arange(1000, 1000 + 2 * n)
    track = np.concatenate([np.repeat(np.arange(20), 10), others])
    per_row = np.where(np.arange(len(kf)) < n, 40 // 20, 10)
    alone = _thinned(track, t, kf, 10, 1)
    shared = _thinned(track, t, kf, per_row, 1)
    assert alone[:n].all()
    assert shared[:n].sum() == 40
    first_last = np.zeros(n, bool)
    first_last[0::10] = first_last[9::10] = True
    assert np.array_equal(shared[:n], first_last)
    assert shared[n:].all()


def test_thinned_by_track_on_the_loop(loop_world) -> None:
    """Thinned per track, the revisit's observations stay: more observations than per fused
    landmark, the drift removed as well."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    poses = {k: odom[k] for k in range(len(odom))}
    res = {
        by: global_bundle_adjustment(
            calib,
            obs,
            poses,
            edges,
            pairs,
            0,
            t_ns,
            GlobalBaParams(max_keyframes_per_landmark=2, thin_by=by),
        )
        for by in ("track", "landmark")
    }
    track, landmark = res["track"], res["landmark"]
    assert track is not None and landmark is not None
    assert track.observations > landmark.observations
    for r in (track, landmark):
        pos = np.array([r.world_from_body[k][:3, 3] for k in poses])
        assert ate_se3_rmse_m(pos, true[:, :3, 3]) < 0.01


def test_outliers_judged_by_the_errors_own_sigma(loop_world) -> None:
    """Tracks 0.6-2 px off (blur, gain steps: a heavier tail than the 0.2 px noise) are inside
    a fixed 3 px outlier threshold; judged against the round's robust sigma they are dropped,
    and the adjusted keyframes come out closer to the truth."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    rng = np.random.default_rng(7)
    bad: dict[int, KeyframeObservations] = {}
    n_bad = 0
    for k, o in obs.items():
        left, right = o.left_px.copy(), o.right_px.copy()
        for px in (left, right):
            hit = rng.random(len(px)) < 0.15
            angle = rng.uniform(0, 2 * np.pi, hit.sum())
            size = rng.uniform(0.6, 2.0, hit.sum())
            px[hit] += np.column_stack([np.cos(angle), np.sin(angle)]) * size[:, None]
            n_bad += int(hit.sum())
        bad[k] = KeyframeObservations(o.landmark_ids, left, right, o.points_cam0)
    poses = {k: odom[k] for k in range(len(odom))}

    def ate(params: GlobalBaParams) -> tuple[float, object]:
        res = global_bundle_adjustment(calib, bad, poses, edges, pairs, 0, t_ns, params)
        assert res is not None
        est = np.array([res.world_from_body[k][:3, 3] for k in poses])
        return ate_se3_rmse_m(est, true[:, :3, 3]), res

    fixed, res_fixed = ate(GlobalBaParams(pixel_sigma_px=1.0, outlier_sigmas=0.0))
    own, res_own = ate(GlobalBaParams())
    assert res_fixed.outlier_limit_px == 3.0  # type: ignore[attr-defined]
    # 0.2 px per axis: the clean rows' sigma; the limit 3 of them (the tail lifts it a little)
    assert 0.55 < res_own.outlier_limit_px < 0.9, res_own.summary()  # type: ignore[attr-defined]
    assert res_own.outliers > 0.8 * n_bad > 10 * res_fixed.outliers  # type: ignore[attr-defined]
    assert own < 0.8 * fixed, (own, fixed)


def test_a_third_round_trims_the_tail_again(loop_world) -> None:
    """``rounds``: each round after the first is solved again without the last round's
    outliers, and a third drops more rows than the second (its limit from the rows the second
    kept); every one stays at the truth (the odometry drifted > 30 mm); 2 is the default."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    rng = np.random.default_rng(5)
    bad: dict[int, KeyframeObservations] = {}
    for k, o in obs.items():
        left = o.left_px.copy()
        hit = rng.random(len(left)) < 0.2  # 20 % of the left rows 0.5-1.5 px off
        angle = rng.uniform(0, 2 * np.pi, hit.sum())
        size = rng.uniform(0.5, 1.5, hit.sum())
        left[hit] += np.column_stack([np.cos(angle), np.sin(angle)]) * size[:, None]
        bad[k] = KeyframeObservations(o.landmark_ids, left, o.right_px, o.points_cam0)
    poses = {k: odom[k] for k in range(len(odom))}
    res: dict[int, tuple[float, GlobalBaResult]] = {}
    for n in (1, 2, 3):
        r = global_bundle_adjustment(
            calib, bad, poses, edges, pairs, 0, t_ns, GlobalBaParams(rounds=n)
        )
        assert r is not None
        est = np.array([r.world_from_body[k][:3, 3] for k in poses])
        res[n] = (ate_se3_rmse_m(est, true[:, :3, 3]), r)
    default = global_bundle_adjustment(calib, bad, poses, edges, pairs, 0, t_ns, GlobalBaParams())
    assert default is not None
    for k in poses:
        np.testing.assert_array_equal(default.world_from_body[k], res[2][1].world_from_body[k])
    assert not np.array_equal(res[1][1].world_from_body[5], res[2][1].world_from_body[5])
    assert res[3][1].outliers > res[2][1].outliers > 0
    # the limit reported is the first round's, whatever the rounds
    assert res[3][1].outlier_limit_px == res[2][1].outlier_limit_px
    assert max(a for a, _ in res.values()) < 0.002, {n: a for n, (a, _) in res.items()}


def test_outlier_limit_is_three_robust_sigmas() -> None:
    rng = np.random.default_rng(1)
    e = np.linalg.norm(rng.normal(0, 0.25, (20000, 2)), axis=1)
    inf = np.full(5, np.inf)  # rows already left out
    p = GlobalBaParams(outlier_sigmas=3.0)
    assert _outlier_limit(np.r_[e[:10000], inf], e[10000:], p) == pytest.approx(0.75, rel=0.03)
    assert _outlier_limit(e, e, GlobalBaParams(outlier_sigmas=0.0)) == 3.0
    assert _outlier_limit(5 * e, e, GlobalBaParams(outlier_sigmas=30.0)) == 3.0  # at most 3 px


def test_keyframe_sigma_factors() -> None:
    """A keyframe's factor is its median error over the round's, in [1, max], to 0.1."""
    rng = np.random.default_rng(2)
    kf_index = np.repeat(np.arange(4), 500)
    scale = np.array([1.0, 1.0, 2.0, 9.0])[kf_index]
    e = np.linalg.norm(rng.normal(0, 0.2, (len(kf_index), 2)), axis=1) * scale
    e_r = np.full(len(e), np.inf)  # no right observations
    overall = np.median(e)
    f = _keyframe_sigma_factors(e, e_r, kf_index, 5, GlobalBaParams(keyframe_sigma_max=3.0))
    assert f is not None
    assert f[0] == f[1] == 1.0  # below the round's median: the plain sigma
    med2 = np.median(e[kf_index == 2])
    assert f[2] == pytest.approx(round(med2 / overall, 1))
    assert f[3] == 3.0  # clipped
    assert f[4] == 1.0  # a keyframe without observations
    assert (
        _keyframe_sigma_factors(e[:1000], e_r[:1000], kf_index[:1000], 2, GlobalBaParams()) is None
    )


def test_noisy_keyframes_weigh_less(loop_world) -> None:
    """Keyframes whose observations are 5x noisier (dark, high-gain, blurred frames) given the
    larger sigma their own residuals show: the adjusted keyframes come out closer to the truth."""
    calib, obs, true, odom, edges, pairs, t_ns = loop_world
    rng = np.random.default_rng(11)
    noisy = {}
    for k, o in obs.items():
        if k % 4 == 1:  # every fourth keyframe: 1 px per axis instead of 0.2
            left = o.left_px + rng.normal(0, 1.0, o.left_px.shape)
            right = o.right_px + rng.normal(0, 1.0, o.right_px.shape)
            noisy[k] = KeyframeObservations(o.landmark_ids, left, right, o.points_cam0)
        else:
            noisy[k] = o
    poses = {k: odom[k] for k in range(len(odom))}

    def ate(params: GlobalBaParams) -> float:
        res = global_bundle_adjustment(calib, noisy, poses, edges, pairs, 0, t_ns, params)
        assert res is not None
        est = np.array([res.world_from_body[k][:3, 3] for k in poses])
        return ate_se3_rmse_m(est, true[:, :3, 3])

    # no outlier round, so the noisy keyframes keep their observations either way
    plain = ate(GlobalBaParams(outlier_sigmas=0.0, outlier_px=100.0))
    weighed = ate(GlobalBaParams(outlier_sigmas=0.0, outlier_px=100.0, keyframe_sigma_max=8.0))
    assert weighed < 0.85 * plain, (weighed, plain)
