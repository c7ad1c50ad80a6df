"""The monocular start redone when the smoother slips (``backend.mono_reinit_residual_m``,
issue 18): a smoother whose positions stop being a similarity of the IMU's trajectory is
detected by the scale check's IMU-fit residual and dropped, and the start's retry path starts a
new one."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from datasets.synth.vio_world import SimWorld, generate_world
from slam.backend import smoother
from slam.backend.config import BackendConfig
from slam.backend.smoother import VioBackend, X
from slam.core.calibration import Calibration
from slam.core.messages import Estimate, ImuSample, Keyframe

SLIP_AFTER_S = 2.5  # after the start: where room-figure8's delayed smoothers slipped
SLIP = 0.3  # grows to 30 % over 1.5 s (monolag20: 15-30 %)


class _SlippingBackend(VioBackend):
    """The first smoother's keyframe positions stretched, from ``SLIP_AFTER_S`` after its start,
    by a factor growing to ``1 + SLIP`` about where they were then: what a delayed run's
    smoother did (its scale slips within 1-2 s). A restarted smoother is left alone."""

    def _add_state(self, kf: Keyframe, pose_vo: np.ndarray | None, with_visual: bool) -> None:
        super()._add_state(kf, pose_vo, with_visual)
        if self._restarts or self.stats.mono_reinits:
            return
        t0 = self.stats.init_t_ns + int(SLIP_AFTER_S * 1e9)
        if kf.t_ns <= t0:
            return
        if not hasattr(self, "slip_centre"):
            self.slip_centre = self._values.atPose3(X(self._states[-2].k)).translation()
        for s in self._states:
            if s.t_ns <= t0:
                continue
            f = 1.0 + SLIP * min(1.0, (s.t_ns - t0) * 1e-9 / 1.5)
            pose = self._values.atPose3(X(s.k))
            p = self.slip_centre + f * (pose.translation() - self.slip_centre)
            self._values.update(X(s.k), gtsam.Pose3(pose.rotation(), p))


def _mono(world: SimWorld) -> Calibration:
    return Calibration(cameras=(world.calibration.cameras[0],), imu=world.calibration.imu)


def _run(backend: VioBackend, world: SimWorld) -> list[tuple[Keyframe, Estimate]]:
    out = []
    for m in world.messages():
        if isinstance(m, ImuSample):
            backend.add_imu(m)
        else:
            est = backend.add_keyframe(m)
            if est is not None:
                out.append((m, est))
    return out


CFG = BackendConfig(
    mono_scale_check_window_s=5.0,
    lag_s=2.0,
    min_keyframes_per_landmark=3,
    time_offset_online=False,
    mono_reinit_residual_m=0.01,
    mono_reinit_max=1,
    landmark_model="projection",
)


@pytest.fixture(scope="module")
def world() -> SimWorld:
    # a front end's VO within 0.2 mm per keyframe, as the real one's over a start's window
    return generate_world(
        duration_s=10.0,
        seed=0,
        start_s=3.0,
        landmarks_per_keyframe=100,
        vo_step_sigma_m=0.0002,
        vo_step_sigma_rad=0.00005,
    )


@pytest.fixture(autouse=True)
def _vo_as_it_is(monkeypatch):
    """The simulated keyframes' VO poses go to the start's alignment as they are: the pose
    refinement is for a real front end's drifting scale (the world's points are not those of a
    map the poses were tracked on)."""
    monkeypatch.setattr(smoother, "refine_vo_poses", lambda poses, *args, **kwargs: poses)


def test_a_slipping_smoother_is_detected_and_the_start_redone(world):
    """The slip is caught by the check's residual within 2 s of its onset (the smoother's own
    states could not say by how much it slipped), the smoother is dropped, the estimates are
    uninitialised (the front end does not apply them) until the start's alignment is accepted
    again on the keyframes from then on, and the new start is metric and where the truth is."""
    backend = _SlippingBackend(_mono(world), CFG)
    out = _run(backend, world)
    st = backend.stats
    assert st.mono_reinits == 1
    start_ns = st.init_t_ns
    reinit = [c for c in st.mono_scale_checks if c.get("reinit")]
    assert len(reinit) == 1 and reinit[0]["residual_m"] > CFG.mono_reinit_residual_m
    slip_ns = start_ns + int(SLIP_AFTER_S * 1e9)
    assert slip_ns < reinit[0]["t_ns"] <= slip_ns + 2_000_000_000
    # before the slip, the checks' residuals are a few mm
    fits = [c for c in st.mono_scale_checks if "reinit" in c]  # the re-initialisation's fits
    before = [c["residual_m"] for c in fits if c["t_ns"] <= slip_ns]
    assert before and max(before) < 0.005
    after = [(kf, e) for kf, e in out if kf.t_ns >= reinit[0]["t_ns"]]
    assert not after[0][1].initialized  # dropped at once
    restarted = [(kf, e) for kf, e in after if e.initialized]
    assert restarted, "the start was not redone"
    first_kf, first = restarted[0]
    assert first.restarts == 1 and all(e.restarts == 1 for _, e in restarted)
    assert (first_kf.t_ns - reinit[0]["t_ns"]) * 1e-9 < 3.0
    assert first.vo_scale == pytest.approx(1.0, abs=0.03)  # the world's VO is metric
    # the new smoother keeps its scale: its keyframes against the truth after a similarity
    ids = [kf.keyframe_id for kf, _ in restarted]
    gt = {k.keyframe_id: g for k, g in zip(world.keyframes, world.world_from_body_gt)}
    last = restarted[-1][1]
    est_p = np.array([last.keyframe_poses[i][:3, 3] for i in ids if i in last.keyframe_poses])
    gt_p = np.array([gt[i][:3, 3] for i in ids if i in last.keyframe_poses])
    spread_est = np.linalg.norm(est_p - est_p.mean(axis=0), axis=1).sum()
    spread_gt = np.linalg.norm(gt_p - gt_p.mean(axis=0), axis=1).sum()
    assert spread_est / spread_gt == pytest.approx(1.0, abs=0.03)
    assert st.init_state == "initialised"


def test_a_smoother_that_does_not_slip_is_left_alone(world):
    """The same world without the slip: every check's residual is a few mm, no re-start."""
    backend = VioBackend(_mono(world), CFG)
    out = _run(backend, world)
    assert backend.stats.mono_reinits == 0
    residuals = [c["residual_m"] for c in backend.stats.mono_scale_checks if "reinit" in c]
    assert residuals and max(residuals) < 0.005
    assert all(e.restarts == 0 for _, e in out)
