"""Configuration of loop closure and relocalisation (nest under ``SlamConfig`` as ``loop``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from slam.core.bounds import bounded


@dataclass
class LoopClosureConfig:
    """Place recognition, geometric verification, plausibility gates and pose-graph weights."""

    max_orb_features: int = bounded(600, ge=1)
    """ORB keypoints per keyframe image for the BoW vector and the query side of PnP."""
    exclude_recent_s: float = bounded(15.0, ge=0)
    """Never match keyframes of the last this many seconds (same place, not a loop)."""
    exclude_recent_keyframes: int = bounded(10, ge=0)
    """... nor the last this many keyframes."""
    min_eligible_keyframes: int = bounded(10, ge=0)
    """No detection until this many keyframes are older than the excluded recent ones."""
    min_consecutive: int = bounded(3, ge=1)
    """Temporal consistency: consecutive keyframe queries agreeing on the place before a loop
    is verified."""
    min_normalised_score: float = bounded(0.3, ge=0)
    """BoW score / score against the recent neighbours needed by a candidate."""
    candidates_to_verify: int = bounded(3, ge=1)
    """Verify up to this many keyframes of the winning island (best score first)."""
    # bounds: a PnP pose needs 4 points (solvePnPRansac asserts it)
    min_inliers: int = bounded(30, ge=4)
    """PnP inliers needed to accept a loop."""
    min_inlier_ratio: float = bounded(0.35, ge=0, le=1)
    """... making up at least this fraction of the descriptor matches."""
    reprojection_px: float = bounded(2.5, gt=0)
    """PnP RANSAC inlier threshold, pixels."""
    guided_radius_px: float = bounded(0.0, ge=0)
    """Landmark-to-landmark verification (loops and the global adjustment's fusion search):
    with this above 0, a candidate the whole-set matching cannot verify is tried again: a
    RANSAC pose with at least ``guided_min_inliers`` inliers is searched again by projection
    (ORB-SLAM's search by projection: each candidate landmark matched among the query's
    landmarks within this radius of where the pose puts it, ``verify.guided_matches``), and
    that search's inliers are what ``min_inliers`` and ``min_inlier_ratio`` judge. 0: off.
    Off everywhere: with 8 the monocular run on three fair V1_01 renders accepts 15 / 11 / 12
    loops instead of 11 / 9 / 9 (one 67 mm off the truth) and its loop-closed Sim(3) ATE
    falls 1.69 / 2.26 / 3.39 -> 1.62 / 2.23 / 2.38 mm, but the SE(3) ATE, which is the map's
    0.3-0.45 % scale error, moves 8.34 / 6.14 / 7.90 -> 8.49 / 6.14 / 7.69 (the suite's
    room-loop s2 and hall s4 byte-identical; BENCHMARKS.md, v101loops20)."""
    guided_min_inliers: int = bounded(12, ge=4, le_field="min_inliers")
    """... RANSAC inliers (and descriptor matches) needed before that search."""
    gate_base_m: float = bounded(0.3, ge=0)
    """Plausibility gate: a loop may move the query keyframe by at most gate_base_m +
    gate_ratio * (odometry path length since the candidate) ..."""
    gate_ratio: float = bounded(0.05, ge=0)
    """... (5% of the path: generous for VIO drift, far below aliased places metres apart)."""
    gate_base_deg: float = bounded(4.0, ge=0, le=180)
    """... and rotate it by at most gate_base_deg + gate_deg_per_m * path length."""
    gate_deg_per_m: float = bounded(0.5, ge=0)
    """Rotation drift allowance per metre of path, degrees."""
    confirm_translation_m: float = bounded(0.2, gt=0)
    """Loops between different map segments (no odometry between them) need a second verified
    loop whose implied alignment agrees within this translation ..."""
    confirm_rotation_deg: float = bounded(3.0, gt=0, le=180)
    """... and this rotation."""
    confirm_within_keyframes: int = bounded(10, ge=1)
    """The confirming loop must come within this many keyframes of the first."""
    min_keyframes_between_loops: int = bounded(5, ge=0)
    """After an accepted loop, skip verification for this many keyframes (the next ones see
    the same place and add little)."""
    # bounds: the floor terms keep a zero-length, zero-time edge's information finite
    odom_sigma_m: float = bounded(0.001, gt=0)
    """Odometry edge translation sigma (per axis), metres: the root sum of squares of this,
    odom_sigma_ratio * edge length and odom_sigma_m_per_sqrt_s * sqrt(edge duration)."""
    odom_sigma_ratio: float = bounded(0.005, ge=0)
    """Odometry translation sigma per metre of edge length."""
    odom_sigma_m_per_sqrt_s: float = bounded(0.004, ge=0)
    """Odometry translation random walk, m/sqrt(s) (measured on the synthetic hall: ~2 mm per
    0.2 s keyframe edge, growing as the square root over 10-100 edges)."""
    # bounds: as odom_sigma_m
    odom_sigma_rad: float = bounded(0.0001, gt=0)
    """Odometry edge rotation sigma (per axis), radians: the root sum of squares of this,
    odom_sigma_rad_ratio * edge rotation angle and odom_sigma_rad_per_sqrt_s * sqrt(duration)."""
    odom_sigma_rad_ratio: float = bounded(0.01, ge=0)
    """Odometry rotation sigma per radian turned."""
    odom_sigma_rad_per_sqrt_s: float = bounded(0.0007, ge=0)
    """Odometry rotation random walk, rad/sqrt(s) (measured: ~0.02 deg per 0.2 s edge)."""
    loop_sigma_m: float = bounded(0.01, gt=0)
    """Loop edge translation sigma (landmark-to-landmark verification), metres."""
    loop_sigma_rad: float = bounded(0.003, gt=0)
    """Loop edge rotation sigma (landmark-to-landmark verification), radians."""
    patch_refinement: bool = True
    """Refine a landmark-verified loop on every landmark of both keyframes that it puts in the
    other image, each fitted there by its patch (``verify.refine_on_patches``), and weight the
    edge by the fit's information times ``patch_information_scale`` instead of the loop
    sigmas. Keeps each keyframe's left image (0.36 MB at 752x480). Measured: BENCHMARKS.md."""
    patch_information_scale: float = bounded(0.01, gt=0, le=1)
    """The patch fit's information is multiplied by this: the fit sees the pixels' noise, not
    the landmarks' depth errors (measured on room-figure8: its chi2 against the truth was ~100x
    the degrees of freedom)."""
    patch_max_change_m: float = bounded(0.05, gt=0)
    """A patch refinement moving the descriptor pose more than this (or
    ``patch_max_change_deg``) is discarded (the descriptor pose stays)."""
    patch_max_change_deg: float = bounded(1.0, gt=0, le=180)
    """See ``patch_max_change_m``."""
    covisibility_edges: Literal["off", "found", "tracked"] = "off"
    """Pose-graph edges between keyframes that share landmarks across a gap: from a keyframe
    to the older keyframe that first saw the largest number of its landmarks, fitted on
    patches from the odometry's relative pose (needs ``patch_refinement``), so that a loop
    correction keeps the tie to the old map that map reuse gives the odometry. Counted
    landmarks: those the front end ``found`` again at this keyframe (map reuse), or every
    ``tracked`` one; ``off``: none. Off by default: sequential live ATE with ``found``
    figure8 3.46 -> 3.62 mm, aggressive 3.52 -> 3.64 (loop-closed 2.15 -> 1.87), hall 15.91
    -> 15.43, V1_01 12.05 -> 11.98 (BENCHMARKS.md, "Covisibility edges")."""
    covisibility_min_landmarks: int = bounded(10, ge=1)
    """... when it sees at least this many landmarks that keyframe first saw ..."""
    covisibility_min_gap_s: float = bounded(3.0, ge=0)
    """... and that keyframe is at least this much older (another pass)."""
    live_correction: Literal["unanchored", "latest"] = "latest"
    """The loop correction the live pose (``trajectory.tum``) is published under: its
    segment's latest (``map_from_odom``) for every frame (``latest``), or for frames not
    tracked on old landmarks only (``unanchored``: those get their odometry, which map reuse
    ties to the old map). Measured with patch-refined edges and ``pgo_align_to_odometry``
    (BENCHMARKS.md, "Precise loop edges" and "After this session's merges"): sequential live
    ATE se3 with ``unanchored`` and ``latest``: room-figure8 4.18 and 3.46 mm, room-aggressive
    3.38 and 3.52, hall 15.92 and 15.91, the V1_01 flight 12.98 and 12.05."""
    pgo_align_to_odometry: bool = True
    """Move each pose-graph result rigidly onto the odometry poses of its keyframes (least
    squares on positions) instead of leaving it where its fixed oldest keyframe holds it: the
    map frame then stays that of the odometry the live pose was published in before (with
    ``live_correction: latest``, room-figure8's live ATE 3.69 -> 3.40 mm, the hall's 16.8 ->
    14.9). Every keyframe moves a little at each correction (the mapper re-integrates those
    past its threshold)."""
    orb_loop_sigma_factor: float = bounded(3.0, gt=0)
    """Loops verified with whole-image ORB keypoints (when landmark to landmark fails) get
    sigmas this many times larger (measured: ~4x the error)."""
    robust: str = "gnc"
    """Robust treatment of loop edges in PGO: gnc (graduated non-convexity, truncated least
    squares: outliers get weight 0), cauchy, huber or none."""
    debug_graph: bool = False
    """Put the final pose graph in the run's stats (``loop_closure.graph``: keyframe times,
    segments, odometry and corrected poses, loop edges) for offline analysis."""
    robust_sigma_scale: float = bounded(4.0, gt=0)
    """The robust kernel judges loop edges as if every sigma were this many times larger
    (GNC: inlier chi2 bound 16.8 x scale^2). The sigmas model VIO drift, and scaling them all
    leaves the optimum unchanged; but a true loop after more drift than that (stereo VO
    without IMU, a dead-reckoned gap) must survive, while false loops metres off still fail."""
    global_ba: bool = True
    """At the end of a run with loops, re-estimate every keyframe and landmark together, with
    the landmarks the loops matched fused (``slam.loop.global_ba``): the loop-closed trajectory
    then no longer inherits the first pass's odometry error."""
    global_ba_budget_fraction: float = bounded(0.1, ge=0, le=10)
    """Time budget of the global adjustment (its fusion search included), as a fraction of the
    time its keyframes span; past it the adjustment keeps the estimate so far (stats.json
    ``loop_closure.global_ba.time_boxed``). 0: no limit. Accuracy and time with and without:
    BENCHMARKS.md."""
    global_ba_grace_s: float = bounded(1.0, ge=0, le=600)
    """In concurrent runs, how long past its time budget the end of the run waits for the
    global adjustment before it stops it and keeps the pose graph's result (stats.json
    ``loop_closure.global_ba_skipped`` says so). Its iterations keep to the budget; its graph
    and first iteration cannot be cut: on a busy machine they overran it by up to 3.2 s."""
    global_ba_min_budget_share: float = bounded(0.4, ge=0, le=1)
    """The global adjustment starts only when at least this share of its time budget is left
    once the loop backlog is done (the budget counts from the front end's last frame). Its
    graph and first iteration cannot be cut: about 1 s on room-aggressive on an idle machine
    and 2-3 s beside busy processes, where, started with a sliver of the budget left, it
    overran it by seconds (BENCHMARKS.md). Skipped, the pose graph's result stays (stats.json
    ``loop_closure.global_ba_skipped`` says why)."""
    global_ba_fusion_budget_share: float = bounded(0.5, gt=0, le=1)
    """Share of that budget the fusion search may use; past it, it stops (having visited the
    keyframes spread over the run)."""
    global_ba_max_keyframes_per_landmark: int = bounded(10, ge=0)
    """Observations kept per landmark in the global adjustment, spread over the keyframes
    that saw it (0: all). 10 made an iteration 3-4x cheaper, so the time-boxed adjustment
    converges where it did one iteration before (BENCHMARKS.md, "End of run")."""
    global_ba_thin_by: Literal["track", "landmark"] = "track"
    """What that limit counts over: each front-end ``track`` (a landmark id over one
    ``max_track_s`` span, before fusion, so every pass over a place keeps its share) or each
    fused ``landmark`` (the revisits' observations lose out to the first pass's: sequential
    loop-closed mm, landmark / track with the shared limit below, hall 5.60 / 5.25, room-loop
    1.43 / 1.29, room-figure8 2.16 / 2.02, room-aggressive 1.69 / 1.75; BENCHMARKS.md)."""
    global_ba_max_observations_per_landmark: int = bounded(40, ge=0)
    """With ``global_ba_thin_by: track``: the keyframe observations a fused landmark's tracks
    share (each keeps this divided by their number, at least 2; 0: no shared limit). Where
    every pass fuses into the same few landmarks (a small room), their elimination makes
    dense blocks over all the keyframes that saw them: without it, room-aggressive's
    adjustment did not fit its budget at ``--speed max`` (its first iteration allocated
    0.9 GB)."""
    global_ba_pixel_sigma_px: float = bounded(0.3, gt=0)
    """Reprojection sigma of the global adjustment, pixels (its Huber kernel starts at 1.345
    of them). Its tracks' errors against the truth: median 0.08 px on the clean suite, 0.11
    with ``--camera realistic``; at 1 px the kernel let 1 px errors count fully (keyframe ATE
    of room-loop's adjustment, clean / realistic mm: 0.75 / 1.65 at 1.0, 0.43 / 0.59 at 0.3
    with ``global_ba_outlier_sigmas`` 3; BENCHMARKS.md, "real17")."""
    global_ba_outlier_sigmas: float = bounded(3.0, ge=0)
    """After each round of the global adjustment, observations reprojecting farther than this
    many robust sigmas of the round's errors (median / sqrt(2 ln 2)) are dropped, at most
    3 px (0: 3 px alone). The errors' tail follows the cameras: auto-exposure, blur and noise
    put more tracks 0.3-1 px off, which a fixed 3 px threshold kept. The fitted errors are
    smaller than the tracks' (landmarks seen by few keyframes fit them closely): on the suite
    the limit came out 0.2-0.7 px and dropped 20-29 % of the observations."""
    global_ba_keyframe_sigma_max: float = bounded(1.0, ge=1, le=10)
    """After the global adjustment's first round, a keyframe whose own reprojection errors
    (median) are larger than the round's has its pixel sigma grown by the ratio, at most this
    factor (1: off, every keyframe at ``global_ba_pixel_sigma_px``). Dark, high-gain, blurred
    frames track worse (realistic room-aggressive: 0.12 px median against the truth at 0-4 ms
    exposures, 0.27-0.31 px at 8-11 ms). Off by default: 2 took the adjustment's keyframe ATE
    4-6 % lower on three realistic room-aggressive renders, but 4-5 % higher on clean
    room-loop and hall (BENCHMARKS.md, agg17b)."""
    global_ba_rounds: int = bounded(2, ge=1, le=10)
    """The global adjustment's solves, each after the last one's outliers were dropped
    (``slam.loop.global_ba.GlobalBaParams.rounds``). 3 took room-aggressive's adjustment
    (keyframe ATE, offline on the runs' inputs) 1-15 % closer to the truth on clean renders
    and 3-11 % on realistic ones, so the realistic/clean ratio grew; off (2) until measured
    on the whole suite (BENCHMARKS.md, agg17d)."""
    global_ba_odometry_sigma_scale: float = bounded(0.7, ge=0)
    """The odometry edges enter the global adjustment with their pose-graph sigmas times this
    (0: left out). Held tighter (0.3), they passed the odometry's scale error (0.05-0.1 % on
    the hall) into the adjusted map. Sequential loop-closed mm for 0.3 / 0.7 / 1.0: hall 5.25 /
    4.26 / 4.04, room-loop 1.29 / 1.01 / 0.98, room-aggressive 1.75 / 1.81 / 1.88,
    room-figure8 2.02 / 1.93 / 1.99 (BENCHMARKS.md)."""
    global_ba_imu: bool = True
    """IMU factors in the global adjustment (visual-inertial full adjustment, as ORB-SLAM3's):
    the back end hands over each keyframe's final velocity and biases and the raw IMU readings
    from the keyframe before it; consecutive keyframes are joined by a ``CombinedImuFactor``
    in place of their odometry edge, and after the first round the IMU's scale and axis
    misalignment are fitted to the adjusted keyframes over the whole run and the readings
    re-integrated through them for the second (``slam.loop.global_ba``). Used where the run
    has an IMU (nothing changes for ``stereo-vo``). Sequential loop-closed mm off -> on:
    room-aggressive clean 0.745 / 0.775 / 0.753 -> 0.468 / 0.502 / 0.569 (seeds 3 / 13 / 23),
    realistic 1.388 / 1.032 / 1.250 -> 0.871 / 0.675 / 0.906; clean room-figure8 0.701 ->
    0.615, room-loop 0.523 -> 0.524, hall 3.119 -> 2.949; realistic room-figure8 0.855 ->
    0.894, room-loop 0.593 -> 0.589, hall 4.755 -> 4.637; monocular room-figure8 15.07 -> 2.31
    (BENCHMARKS.md, "gaimu17" and the thirteenth session)."""
    global_ba_imu_refit_max_std: float = bounded(0.0007, gt=0, le=0.1)
    """The global adjustment's IMU refit (``GlobalBaParams.imu_refit_max_std``): a sensor's
    fitted correction matrix is used only when the standard deviations of its three scale
    factors are all below this (fraction; else that sensor stays as read), and the second
    round's tighter IMU allowance (0.1 %) applies only when both sensors' are. On room-loop
    the accelerometer's fit is 0.09-0.11 % uncertain, so at 0.0007 it is never used there;
    0.0015 uses it (within 0.11 % of the truth on three realistic renders) and makes the
    loop-closed ATE worse on 10 of 12 room-loop runs (clean, realistic, each half alone): the
    tight allowance then also holds the gyro's fit, whose y-axis error (0.05-0.15 %) its 0.03 %
    standard deviation understates (likely why; not isolated). Main's 0.0007 by default
    (BENCHMARKS.md, real21)."""
    global_ba_imu_midpoint: bool = False
    """The global adjustment's IMU factors integrate each reading with the rotation at the
    middle of its piece instead of GTSAM's at its start (``slam.backend.imu.integrate_pieces``),
    removing a systematic acceleration (the specific force times half a piece's rotation) that
    a monocular map's scale, held by the IMU alone, follows. On in ``euroc-mono-imu``
    (monocular loop-closed room-figure8 / room-loop, BENCHMARKS.md "mono18h"); off for stereo,
    whose scale the stereo pairs hold."""
    global_ba_imu_odometry_rotation_only: bool = False
    """With ``global_ba_imu``: the odometry edges that no IMU factor replaces (keyframes the back
    end handed no state for, e.g. those in the smoother's window when a monocular scale check
    restarted it) hold only the relative rotation in the global adjustment; their translation,
    the monocular smoother's at its scale of the time, is left out
    (``GlobalBaParams.imu_odometry_rotation_only``). On in ``euroc-mono-imu``: room-figure8
    seed 21's 11 such edges took the adjusted map's scale to 1.129 (BENCHMARKS.md, mono18i).
    Stereo keeps them: its odometry's scale is the stereo pairs'."""
    global_ba_imu_accel_walk_factor: float = bounded(1.0, gt=0)
    """The global adjustment's IMU factors model the accelerometer bias's random walk as the
    calibration's times this (``GlobalBaParams.imu_accel_walk_factor``). For an IMU whose bias
    wanders further than its calibration says (EuRoC V1_01: 0.03-0.18 m/s^2 within 10 s, ~10x
    the calibrated walk), where the monocular map's scale otherwise takes up the wander.
    Monocular loop-closed ATE on three fair V1_01 renders, 1 -> 10 (with the gyro's 30): 10.06
    / 14.99 / 9.59 -> 4.69 / 9.34 / 4.07 mm. On the suite's renders, whose simulated bias
    follows the calibrated walk, the looser bias takes up part of a monocular scale error
    instead (keyframes, offline: room-figure8 s1 1.52 -> 10.86 mm, room-loop s2 0.41 -> 0.77;
    BENCHMARKS.md, v101mono18). The prior on the back end's accelerometer bias estimates is
    loosened by the same factor. Off (1) by default; ``euroc-mono-imu`` sets 10 (the gyro's
    stays 1) behind ``global_ba_imu_walk_gate`` (1.25), which passes V1_01's IMU and none of the
    suite's (BENCHMARKS.md, v101loop19), now 1000 with ``global_ba_imu_accel_bias_smoothing``
    (BENCHMARKS.md, v101walk20)."""
    global_ba_imu_gyro_walk_factor: float = bounded(1.0, gt=0)
    """The same for the gyro bias's random walk (``GlobalBaParams.imu_gyro_walk_factor``)."""
    global_ba_imu_walk_gate: float = bounded(0.0, ge=0)
    """With it above 0, each of the two walk factors above applies only where the back end's
    estimates of that sensor's bias wandered at least this many times as far as the calibrated
    random walk allows (``GlobalBaParams.imu_walk_gate``, ``slam.loop.global_ba.bias_wander``:
    the median over keyframes of the squared change over 10 s against the walk's variance;
    stats.json ``loop_closure.global_ba.imu_*_bias_wander`` and ``imu_*_walk_factor``); 0: they
    always apply. ``euroc-mono-imu``: 1.25 (the fair V1_01 renders' accelerometer wander
    1.51-1.69 since ``backend.keyframe_waits_for_imu``, 1.8-2.3 before; the suite's at most
    1.05; BENCHMARKS.md, v101loop19 and speedmax21)."""
    global_ba_imu_accel_bias_smoothing: float = bounded(0.0, ge=0)
    """With it above 0, where ``global_ba_imu_accel_walk_factor`` applies (behind the gate):
    the accelerometer bias is also held by a second-order random walk of this density (m/s^2
    per s^1.5; ``GlobalBaParams.imu_accel_bias_smoothing``), free to drift slowly but not to
    follow the motion, and the bias walks become factors of their own beside ``ImuFactor``s,
    so the walk factor no longer widens the IMU factors' noise. ``euroc-mono-imu``: 0.015 with
    the accelerometer's walk factor 1000 (BENCHMARKS.md, v101walk20). 0: none."""
    global_ba_fusion: bool = True
    """Before the global adjustment, match every keyframe landmark to landmark against the
    keyframes of *other passes* near its corrected pose (ORB-SLAM's loop fusion), so the
    adjustment fuses the revisits' landmarks everywhere and not only at the loops."""
    global_ba_fusion_radius_m: float = bounded(0.5, gt=0)
    """Fusion candidates: corrected positions at most this far apart ..."""
    # bounds: the fusion score divides by 1 - cos(angle)
    global_ba_fusion_angle_deg: float = bounded(30.0, gt=0, le=180)
    """... viewing directions (camera z) at most this many degrees apart ..."""
    global_ba_fusion_min_gap_s: float = bounded(3.0, ge=0)
    """... and at least this far apart in time (another pass, not the same track)."""
    global_ba_fusion_candidates: int = bounded(2, ge=1)
    """Per keyframe, match at most this many candidates, each from a different pass."""
    global_ba_fusion_gate_m: float = bounded(0.1, gt=0)
    """A fusion match is kept only when its relative pose agrees with the corrected poses
    within this translation ..."""
    global_ba_fusion_gate_deg: float = bounded(3.0, gt=0, le=180)
    """... and this rotation."""
    pgo_process: bool = True
    """Run pose-graph optimisation in a worker process (GTSAM holds the GIL)."""
    reloc_candidates: int = bounded(3, ge=1)
    """Relocalisation: verify up to this many best BoW hits."""
    # bounds: PnP against the query image's ORB keypoints: at most max_orb_features
    reloc_min_inliers: int = bounded(15, ge=4, le_field="max_orb_features")
    """Relocalisation: PnP inliers needed (measured: after a 2 s blackout on the synthetic loop,
    the best of the last keyframes gives 20-26 inliers of ~200 landmark descriptors). The front
    end also rejects a relocalisation that contradicts its IMU dead-reckoned pose."""
