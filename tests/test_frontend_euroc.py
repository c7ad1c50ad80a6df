"""The front end on real EuRoC V1_01 frames (the vehicle barely moves in these 95 frames)."""

from __future__ import annotations

import numpy as np
from conftest import require

from slam.config import FrontendConfig
from slam.frontend.features import detect_features, track_klt
from slam.frontend.stereo import StereoMatcher
from slam.frontend.tracker import FrontEnd


def _open(shared_data):
    from datasets.open import open_sequence

    return open_sequence(require(shared_data / "euroc_v101_micro"))


def test_real_frames_track_without_loss_and_stay_put(shared_data):
    seq = _open(shared_data)
    fe = FrontEnd(seq.calibration, FrontendConfig())
    positions = []
    states = []
    for frame in seq.iter_frames():
        res, _ = fe.process(frame)
        states.append(res.state)
        assert res.world_from_body is not None, f"frame {frame.index} lost: {res.reason}"
        positions.append(res.world_from_body[:3, 3])
    assert states.count("lost") == 0
    assert fe.stats.segments == 1
    path = float(np.linalg.norm(np.diff(np.array(positions), axis=0), axis=1).sum())
    assert path < 0.05, f"estimated path length {path:.3f} m"


def test_grid_detection_and_klt_forward_backward(shared_data):
    seq = _open(shared_data)
    cfg = FrontendConfig()
    f0, f1 = seq.frame(0), seq.frame(1)
    px = detect_features(f0.left, np.zeros((0, 2)), cfg)
    assert 100 <= len(px) <= cfg.max_features
    tracked, ok = track_klt(f0.left, f1.left, px, cfg)
    assert ok.mean() > 0.8
    # the vehicle is almost still: tracked points barely move
    assert np.median(np.linalg.norm(tracked[ok] - px[ok], axis=1)) < 2.0


def test_stereo_depths_are_plausible(shared_data):
    seq = _open(shared_data)
    cfg = FrontendConfig()
    f = seq.frame(0)
    px = detect_features(f.left, np.zeros((0, 2)), cfg)
    m = StereoMatcher(seq.calibration, cfg).match(f.left, f.right, px)
    assert m.ok.sum() >= 40
    z = m.points_cam0_m[m.ok, 2]
    # the Vicon room: everything seen is between ~0.5 m and ~8 m away
    assert 0.5 < np.median(z) < 8.0
    assert (z > cfg.min_depth_m).all() and (z < cfg.max_depth_m).all()


def test_stereo_from_known_points_finds_the_same_matches(shared_data):
    """Real EuRoC pair: matching from the features' known 3-D points (one pyramid level, no
    backward track) lands on the full search's matches, and keeps nearly all of them; a point
    that predicts the wrong place is not matched there."""
    seq = _open(shared_data)
    cfg = FrontendConfig()
    f = seq.frame(0)
    px = detect_features(f.left, np.zeros((0, 2)), cfg)
    matcher = StereoMatcher(seq.calibration, cfg)
    full = matcher.match(f.left, f.right, px)
    known = np.where(full.ok[:, None], full.points_cam0_m, np.nan)
    again = matcher.match(f.left, f.right, px, known)
    both = full.ok & again.ok
    assert both.sum() >= 0.95 * full.ok.sum()
    err = np.linalg.norm(again.pixels_right[both] - full.pixels_right[both], axis=1)
    assert np.median(err) < 0.05 and np.percentile(err, 95) < 0.3
    wrong = known.copy()
    wrong[:, 2] *= 3.0  # three times too far: the prediction is off by tens of pixels
    shifted = matcher.match(f.left, f.right, px, wrong)
    moved = full.ok & (np.linalg.norm(wrong[:, :2], axis=1) > 0)
    assert (
        shifted.ok[moved]
        & (np.linalg.norm(shifted.pixels_right[moved] - full.pixels_right[moved], axis=1) < 1.0)
    ).mean() < 0.2


def test_pose_goes_out_before_the_keyframe_work(shared_data):
    """``track`` gives the pose with the keyframe's id; ``after_pose`` then makes that very
    keyframe. The pose's latency excludes the keyframe work, which is timed on its own."""
    seq = _open(shared_data)
    cfg = FrontendConfig(keyframe_max_interval_s=0.2)  # still rig: keyframes by time
    fe = FrontEnd(seq.calibration, cfg)
    announced, made = [], []
    for frame in list(seq.iter_frames())[:30]:
        res = fe.track(frame)
        features_at_pose = len(res.feature_pixels)
        kf = fe.after_pose()
        if res.is_keyframe:
            announced.append(res.keyframe_id)
        if kf is not None:
            made.append(kf.keyframe_id)
            assert kf.t_ns == res.t_ns
            if res.state == "tracking":  # a keyframe adds new features after the pose
                assert len(fe.px) >= features_at_pose
    assert len(made) >= 3 and announced == made
    assert len(fe.stats.after_pose_ms) == 30
