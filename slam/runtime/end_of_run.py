"""The end of a run: the trajectories that are known only once the stages have ended.

- the keyframe trajectory: the back end's optimised keyframe poses where it has them (later
  keyframes follow its last by the front end's motion);
- the loop-closed trajectory: every output frame moved by its keyframes' corrections, and at
  the end of the run the frames between two adjusted keyframes integrated from the IMU;
- the final keyframe poses the mapper re-integrates its keyframes at.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from slam.core.geometry import invert_transform, poses_to_matrices, so3_exp_batch, so3_log
from slam.core.messages import ImuBatch, ImuIntrinsics
from slam.core.trajectory import Trajectory
from slam.imu_buffer import ImuBuffer, propagate_pose
from slam.loop.closer import bridge_corrections, loop_closed_poses
from slam.runtime.backend import BackendStage
from slam.runtime.loop import LoopClosureStage
from slam.runtime.outputs import trajectory_from_poses
from slam.runtime.recorder import Recorder

IMU_BRIDGE_MAX_INTERVAL_NS = 1_000_000_000
"""Keyframes farther apart than this are not bridged with the IMU (a gap, a tracking loss)."""


def imu_between_keyframes(
    frame_t_ns: np.ndarray,
    frame_poses: np.ndarray,
    keyframe_rows: np.ndarray,
    frame_segments: np.ndarray,
    imu: ImuBatch,
    gravity_m_s2: float,
    bias_gyro_rad_s: np.ndarray | None = None,
    bias_accel_m_s2: np.ndarray | None = None,
    intrinsics: ImuIntrinsics | None = None,
) -> np.ndarray:
    """``frame_poses`` (N, 4, 4, world_from_body) with every frame strictly between two
    consecutive keyframes (``keyframe_rows``: their rows, increasing) of one map segment, at
    most ``IMU_BRIDGE_MAX_INTERVAL_NS`` apart, dead-reckoned with the IMU from the first and
    pinned to both: the velocity at the first is the one that reaches the second's position
    (``slam.imu_buffer.propagate_pose`` from zero velocity, then the missing displacement
    spread linearly), and the rotation's disagreement with the second is spread over the
    interval. The frames' own poses (tracking, with the loop corrections interpolated between
    keyframes) are noisier than the adjusted keyframes in fast motion: on room-aggressive
    between keyframes 2.0 mm ATE, at keyframes 1.15; from the IMU 1.24 (BENCHMARKS.md).
    Intervals the IMU does not cover keep the given poses. ``bias_*``: (K, 3), the IMU biases
    over the interval that starts at each keyframe (None: zero; the accelerometer's matters
    where keyframes are 0.5 s apart: ``b T^2 / 8`` at the middle). ``intrinsics``: the
    back end's IMU correction matrices (its biases are for readings through them)."""
    out = np.array(frame_poses, dtype=float, copy=True)
    buffer = ImuBuffer(keep_ns=None)  # the whole run's IMU; window(): the samples over [ta, tb]
    buffer.extend_batch(imu)
    buffer.set_intrinsics(intrinsics)
    if len(buffer) < 2 or len(keyframe_rows) < 2:
        return out
    rows = np.asarray(keyframe_rows, dtype=np.int64)
    zero = np.zeros((len(rows), 3))
    bg = zero if bias_gyro_rad_s is None else np.asarray(bias_gyro_rad_s, dtype=float)
    ba = zero if bias_accel_m_s2 is None else np.asarray(bias_accel_m_s2, dtype=float)
    for k, (a, b) in enumerate(zip(rows[:-1].tolist(), rows[1:].tolist(), strict=True)):
        ta, tb = int(frame_t_ns[a]), int(frame_t_ns[b])
        if b - a < 2 or tb - ta > IMU_BRIDGE_MAX_INTERVAL_NS:
            continue
        if len(set(np.asarray(frame_segments[a : b + 1]).tolist())) > 1:
            continue
        samples = buffer.window(ta, tb)
        still = np.zeros(3)
        start = out[a]
        end = propagate_pose(samples, ta, tb, start, still, bg[k], ba[k], gravity_m_s2)
        if end is None:
            continue
        span_s = (tb - ta) * 1e-9
        velocity = (out[b][:3, 3] - end[0][:3, 3]) / span_s
        spin = so3_log(end[0][:3, :3].T @ out[b][:3, :3]).reshape(3)
        for i in range(a + 1, b):
            ti = int(frame_t_ns[i])
            mid = propagate_pose(samples, ta, ti, start, still, bg[k], ba[k], gravity_m_s2)
            if mid is None:
                break
            alpha = (ti - ta) / (tb - ta)
            out[i, :3, :3] = mid[0][:3, :3] @ so3_exp_batch((alpha * spin)[None])[0]
            out[i, :3, 3] = mid[0][:3, 3] + velocity * (ti - ta) * 1e-9
    return out


def keyframe_trajectory(
    frontend_kfs: Trajectory, backend: BackendStage | None, recorder: Recorder
) -> Trajectory:
    """Back-end (optimised) keyframe poses where there are any, else the front end's.

    Keyframes after the back end's last estimate follow it by the front end's motion: an
    interrupted run skips the back end's backlog, and a run stopped just after a late
    initialisation wrote one keyframe of its 15 (the front end's other 14 were lost)."""
    if backend is None or not backend.keyframe_poses:
        return frontend_kfs
    times = recorder.keyframe_times_copy()
    estimated = {k: p for k, p in dict(backend.keyframe_poses).items() if k in times}
    poses = sorted((times[k], p) for k, p in estimated.items())
    if estimated:
        last = max(estimated)
        row_of = {t: i for i, t in enumerate(frontend_kfs.t_ns.tolist())}
        later = sorted(times[k] for k in times if k > last and times[k] in row_of)
        if later and times[last] in row_of:
            # Only these rows to matrices: this runs at every periodic flush, in the main thread.
            rows = [row_of[times[last]]] + [row_of[t] for t in later]
            front = poses_to_matrices(frontend_kfs.positions_m[rows], frontend_kfs.q_wxyz[rows])
            map_from_front = estimated[last] @ invert_transform(front[0])
            poses += [(t, map_from_front @ m) for t, m in zip(later, front[1:], strict=True)]
    return trajectory_from_poses(poses)


def loop_closed_trajectory(
    traj: Trajectory,
    loop: LoopClosureStage,
    smoothed: Callable[[int], bool],
    recorder: Recorder,
    imu: ImuBatch | None = None,
    gravity_m_s2: float = 9.81,
    biases_at: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None,
    intrinsics: ImuIntrinsics | None = None,
) -> Trajectory | None:
    """The loop-closed trajectory (every frame through its keyframes' corrections), or None
    before any keyframe has a correction. With ``imu`` (the end of the run), the frames
    between two corrected keyframes are integrated from the IMU (:func:`imu_between_keyframes`)."""
    if len(traj) == 0:
        return None
    corrections = dict(loop.keyframe_corrections())
    corrected = loop.corrected_keyframe_poses()
    t_ns_of, segment_of = loop.keyframe_times_and_segments()
    kids = [k for k in corrections if k in t_ns_of]
    # Keyframes from before the back end's initialisation only have the front end's
    # pre-gravity-alignment pose, and their odometry edge carries the change of frame
    # (measured on room-figure8: kf 0 and 1 corrected 41 mm off): frames of that time
    # follow the first initialised keyframe instead.
    kids = [k for k in kids if smoothed(k)] or kids
    if not kids:
        return None
    # A keyframe's correction relative to the *output* pose of its own frame where there is
    # one: frames then follow their keyframe by the causal relative motion they were tracked
    # with. (Relative to the keyframe's back-end pose, each frame also carried the
    # difference between the causal and the smoothed estimate of the keyframe: measured
    # on room-figure8 after global BA, 5.6 mm frame ATE against 4.0 mm for the keyframes.)
    # The output poses without the front end's corrections (Recorder.continuous_odometry):
    # a keyframe's correction relative to its frame's pose from before a correction the front
    # end made after it (re-anchoring on the back end's estimate of that keyframe, map reuse:
    # up to 2.3 cm on room-loop, 5 cm on the hall) carried that move into the frames up to
    # the next keyframe (BENCHMARKS.md, "Loop-closed ATE since the restructure").
    # And across each correction, the frame-to-frame motion from the frames around it
    # (bridge_corrections: the undone move is exact only for its rigid part).
    frame_at = {int(t): i for i, t in enumerate(traj.t_ns.tolist())}
    segments = recorder.segments_of_first(len(traj))
    frame_poses = bridge_corrections(
        recorder.continuous_odometry(len(traj)), recorder.correction_frames(len(traj)), segments
    )
    for k in kids:
        i = frame_at.get(int(t_ns_of[k]))
        if i is not None and k in corrected:
            corrections[k] = corrected[k] @ invert_transform(frame_poses[i])
    kf_t = np.array([t_ns_of[k] for k in kids], dtype=np.int64)
    kf_seg = np.array([segment_of[k] for k in kids])
    poses = loop_closed_poses(
        traj.t_ns,
        segments,
        frame_poses,
        kf_t,
        kf_seg,
        np.array([corrections[k] for k in kids]),
    )
    if imu is not None:
        anchors = [k for k in kids if smoothed(k) and int(t_ns_of[k]) in frame_at]
        rows = np.array(sorted(frame_at[int(t_ns_of[k])] for k in anchors), dtype=np.int64)
        bg, ba = (None, None) if biases_at is None else biases_at(traj.t_ns[rows])
        poses = imu_between_keyframes(
            traj.t_ns, poses, rows, segments, imu, gravity_m_s2, bg, ba, intrinsics
        )
    return Trajectory.from_matrices(traj.t_ns, poses)


def final_keyframe_poses(
    keyframes: Trajectory,
    loop: LoopClosureStage | None,
    loop_closed: Trajectory | None,
    smoothed: Callable[[int], bool],
    recorder: Recorder,
) -> dict[int, np.ndarray]:
    """Keyframe t_ns -> final world_from_body for the mapper's re-integration."""
    final = {int(t): p for t, p in zip(keyframes.t_ns, keyframes.matrices(), strict=True)}
    if loop is None:
        return final
    times = recorder.keyframe_times_copy()
    closed_at = (
        {}
        if loop_closed is None
        else dict(zip(loop_closed.t_ns.tolist(), loop_closed.matrices(), strict=True))
    )
    for kid, pose in loop.corrected_keyframe_poses().items():
        if kid not in times:
            continue
        # Before the back end's initialisation the pose graph's pose was 35 mm off on
        # room-figure8: take the loop-closed trajectory's frame there.
        use = pose if smoothed(kid) else closed_at.get(int(times[kid]))
        if use is not None:
            final[times[kid]] = use
    return final
