"""Affine re-fit of tracks against their birth patch (slam/frontend/affine_klt.py)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from datasets.synth import make_synthetic_sequence
from slam.config import FrontendConfig, load_config
from slam.core.errors import SlamError
from slam.frontend.affine_klt import TrackTemplates, build_templates, refine_affine
from tools.bench_klt_drift import track_errors


def _texture(seed: int = 0, size: int = 240) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.uniform(0, 255, (size, size)).astype(np.float32)
    img = cv2.GaussianBlur(img, (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255
    return img.astype(np.uint8)


def _warped(img: np.ndarray, linear: np.ndarray, centre: np.ndarray, shift: np.ndarray):
    """img warped by x' = linear (x - centre) + centre + shift; returns (image, mapping)."""
    m = np.hstack([linear, (centre + shift - linear @ centre)[:, None]])
    out = cv2.warpAffine(img, m, img.shape[::-1], flags=cv2.INTER_CUBIC)
    return out, lambda p: p @ linear.T + m[:, 2]


def test_affine_fit_finds_the_birth_point_under_deformation() -> None:
    img = _texture()
    rot = np.radians(12.0)
    linear = 1.18 * np.array([[np.cos(rot), -np.sin(rot)], [np.sin(rot), np.cos(rot)]])
    linear[0, 1] += 0.06  # a little shear (foreshortening)
    centre = np.array([120.0, 120.0])
    target, mapping = _warped(img, linear, centre, np.array([3.2, -1.7]))
    grid = np.linspace(95, 145, 5)
    pts = np.array([[x, y] for x in grid for y in grid], np.float32)
    truth = mapping(pts.astype(float))
    guess = truth + [0.8, -0.6]  # where frame-to-frame tracking might have left them
    fit = refine_affine(build_templates(img, pts, 7), target, guess, iterations=8)
    assert fit.ok.mean() >= 0.9  # a fit caught in a local minimum is flagged, not used
    err = np.linalg.norm(fit.pts_px - truth, axis=1)[fit.ok]
    assert np.median(err) < 0.03 and err.max() < 0.1
    np.testing.assert_allclose(
        fit.linear[fit.ok], np.broadcast_to(linear, (len(err), 2, 2)), atol=0.01
    )
    # the same points with translation-only KLT (21 px window) land measurably off
    klt, st, _ = cv2.calcOpticalFlowPyrLK(
        img,
        target,
        pts.reshape(-1, 1, 2),
        guess.astype(np.float32).reshape(-1, 1, 2).copy(),
        winSize=(21, 21),
        maxLevel=0,
        flags=cv2.OPTFLOW_USE_INITIAL_FLOW,
    )
    klt_err = np.linalg.norm(klt.reshape(-1, 2) - truth, axis=1)[st.ravel() == 1]
    assert np.median(klt_err) > 5 * np.median(err)


def test_flat_or_failed_patches_keep_their_pixel() -> None:
    img = _texture()
    img[:, :100] = 128  # flat left part
    pts = np.array([[50.0, 120.0], [170.0, 120.0]], np.float32)
    tpl = build_templates(img, pts, 7)
    assert list(tpl.valid) == [False, True]
    far = pts + [0.0, 0.0]
    far[1] += [6.0, 0.0]  # too far from where it fits (more than max_shift_px away)
    fit = refine_affine(tpl, img, far, max_shift_px=2.0)
    assert not fit.ok.any()

    store = TrackTemplates(7, 3)
    store.add(np.array([0, 1]), pts, img)
    out, has_template, refitted = store.refine(np.array([0, 1]), far, img)
    np.testing.assert_array_equal(out, far)
    assert has_template.all() and not refitted.any()


def test_track_templates_follow_the_live_landmarks() -> None:
    img = _texture(1)
    pts = np.array([[60.0 + 15 * i, 100.0 + 7 * (i % 3)] for i in range(8)], np.float32)
    store = TrackTemplates(7, 4)
    store.add(np.arange(5), pts[:5], img)
    store.add(np.array([7, 6, 5]), pts[[7, 6, 5]], img)  # any order within one call
    store.keep_only(np.array([1, 3, 6, 9]))
    assert store.ids.tolist() == [1, 3, 6]
    shifted, mapping = _warped(img, np.eye(2), np.zeros(2), np.array([0.4, -0.3]))
    ids = np.array([6, -1, 3, 2])  # 2 was dropped, -1 has no landmark
    query = pts[[6, 0, 3, 2]]
    out, has_template, refitted = store.refine(ids, query, shifted)
    assert has_template.tolist() == [True, False, True, False]
    assert refitted.tolist() == [True, False, True, False]
    np.testing.assert_allclose(out[[0, 2]], mapping(query[[0, 2]].astype(float)), atol=0.03)
    np.testing.assert_array_equal(out[[1, 3]], query[[1, 3]])
    with pytest.raises(ValueError, match="increasing id order"):
        store.add(np.array([4]), pts[:1], img)
        store.build_pending()
    store.clear()
    assert len(store) == 0


def test_refit_tracks_stay_on_their_surface_point() -> None:
    """Rendered room, true 3-D points from the depth image: after 2 s the re-fitted tracks are
    within 0.15 px (median) of where their point projects, and much closer than KLT alone."""
    seq = make_synthetic_sequence("figure8", duration_s=8.0, seed=1)
    cfg = load_config("euroc-stereo-imu").frontend
    plain = track_errors(seq, 40, 40, cfg, affine=False, check_every=40)[40]
    refit = track_errors(seq, 40, 40, cfg, affine=True, check_every=40)[40]
    assert len(refit) > 100
    assert np.median(refit) < 0.15
    assert np.median(refit) < 0.5 * np.median(plain)


def test_affine_config_errors_are_one_line(tmp_path) -> None:
    assert FrontendConfig().affine_refinement
    bad = tmp_path / "bad.yaml"
    bad.write_text("preset: euroc-stereo-imu\nfrontend:\n  affine_half_window_px: 1\n")
    with pytest.raises(SlamError, match="affine_refinement: false"):
        load_config(str(bad))
