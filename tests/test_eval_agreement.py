"""`slam eval` agrees with evo 1.38 (the reference tool) on every real pair of evo's test data."""

from __future__ import annotations

import io
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest
from conftest import require

from slam.evaluation import evaluate as ev

evo_fi = pytest.importorskip("evo.tools.file_interface")
from evo.core.metrics import PoseRelation, Unit  # noqa: E402
from evo.main_ape import ape as evo_ape  # noqa: E402
from evo.main_rpe import rpe as evo_rpe  # noqa: E402

REL_TOL = 1e-9
EVO_RELATION = {
    "trans": PoseRelation.translation_part,
    "angle_deg": PoseRelation.rotation_angle_deg,
    "angle_rad": PoseRelation.rotation_angle_rad,
    "rot": PoseRelation.rotation_part,
    "full": PoseRelation.full_transformation,
}
# (reference, estimate) as in the issue: KITTI 00 ORB and S-PTAM, fr2/desk ORB, fr1/xyz
# rgbdslam, EuRoC V1_02 vs its native csv, the OpenVINS V1_01 pair.
PAIRS = [
    ("KITTI_00_gt.txt", "KITTI_00_ORB.txt"),
    ("KITTI_00_gt.txt", "KITTI_00_SPTAM.txt"),
    ("fr2_desk_groundtruth.txt", "fr2_desk_ORB.txt"),
    ("freiburg1_xyz-groundtruth.txt", "freiburg1_xyz-rgbdslam.txt"),
    ("V102_groundtruth.csv", "V102.txt"),
    ("from_pr746/V101_gt.txt", "from_pr746/V101_openvins.txt"),
]


@pytest.fixture(scope="module")
def evo_dir(shared_data: Path) -> Path:
    return require(shared_data / "trajectories" / "evo_testdata")


def _evo_read(path: Path, fmt: str):
    """evo's own reader, then drop repeated stamps (keep first) as our --dedupe first does."""
    if fmt == "kitti":
        return evo_fi.read_kitti_poses_file(path)
    traj = (
        evo_fi.read_euroc_csv_trajectory(path)
        if fmt == "euroc"
        else evo_fi.read_tum_trajectory_file(path)
    )
    keep = np.concatenate([[True], np.diff(traj.timestamps) != 0])
    traj.reduce_to_ids(np.nonzero(keep)[0])
    return traj


def _evo_pair(evo_dir: Path, ref_name: str, est_name: str, ref_fmt: str, est_fmt: str):
    ref = _evo_read(evo_dir / ref_name, ref_fmt)
    est = _evo_read(evo_dir / est_name, est_fmt)
    if hasattr(ref, "timestamps") and hasattr(est, "timestamps"):
        ref, est = ref.sync_with(est, max_diff=0.01)
    return ref, est


def _assert_stats_equal(ours: dict, theirs: dict) -> None:
    for key, value in theirs.items():
        # abs: an error that is zero up to round-off (origin alignment's first pose) has no
        # meaningful relative digits
        assert ours[key] == pytest.approx(value, rel=REL_TOL, abs=1e-12), key


@pytest.fixture(scope="module", params=PAIRS, ids=[p[1] for p in PAIRS])
def pair(request, evo_dir: Path):
    ref_name, est_name = request.param
    opts = ev.EvalOptions(dedupe="first")
    ref, est = ev.load_pair(evo_dir / ref_name, evo_dir / est_name, opts)
    return evo_dir, ref_name, est_name, ref, est


@pytest.mark.parametrize(
    "align, relations",
    [
        ("se3", ("trans", "angle_deg", "full", "rot")),
        ("sim3", ("trans",)),
        ("scale", ("trans",)),
        ("origin", ("trans", "angle_rad")),
        ("none", ("trans",)),
    ],
)
def test_ape_matches_evo(pair, align: str, relations: tuple[str, ...]) -> None:
    evo_dir, ref_name, est_name, ref, est = pair
    prepared = ev.prepare(ref, est, ev.EvalOptions(align=align))
    for relation in relations:
        tr, te = _evo_pair(evo_dir, ref_name, est_name, ref.format, est.format)
        res = evo_ape(
            tr,
            te,
            EVO_RELATION[relation],
            align=align in ("se3", "sim3"),
            correct_scale=align in ("sim3", "scale"),
            align_origin=align == "origin",
        )
        ours = ev.ape_of(prepared, relation)
        assert len(ours.errors) == len(res.np_arrays["error_array"])
        _assert_stats_equal(ours.stats, res.stats)


@pytest.mark.parametrize(
    "delta, unit, all_pairs, align",
    [
        (1, "frames", False, "none"),
        (10, "frames", True, "se3"),
        (2.0, "metres", False, "sim3"),
        (1.0, "metres", True, "none"),
    ],
)
def test_rpe_matches_evo(pair, delta, unit, all_pairs, align) -> None:
    evo_dir, ref_name, est_name, ref, est = pair
    prepared = ev.prepare(ref, est, ev.EvalOptions(align=align))
    for relation in ("trans", "angle_deg") if unit == "frames" and not all_pairs else ("trans",):
        tr, te = _evo_pair(evo_dir, ref_name, est_name, ref.format, est.format)
        res = evo_rpe(
            tr,
            te,
            EVO_RELATION[relation],
            delta=delta,
            delta_unit=Unit.frames if unit == "frames" else Unit.meters,
            all_pairs=all_pairs,
            align=align in ("se3", "sim3"),
            correct_scale=align == "sim3",
        )
        ours = ev.rpe_of(prepared, relation, delta, unit, all_pairs)
        assert len(ours.errors) == len(res.np_arrays["error_array"])
        _assert_stats_equal(ours.stats, res.stats)


def test_align_first_n_matches_evo(evo_dir: Path) -> None:
    opts = ev.EvalOptions(align="se3", align_first=200, dedupe="first")
    ref, est = ev.load_pair(evo_dir / "V102_groundtruth.csv", evo_dir / "V102.txt", opts)
    ours = ev.ape_of(ev.prepare(ref, est, opts), "trans")
    tr, te = _evo_pair(evo_dir, "V102_groundtruth.csv", "V102.txt", "euroc", "tum")
    res = evo_ape(tr, te, PoseRelation.translation_part, align=True, n_to_align=200)
    _assert_stats_equal(ours.stats, res.stats)


def _zip_stats(path: Path) -> tuple[dict, np.ndarray]:
    with zipfile.ZipFile(path) as z:
        stats = json.loads(z.read("stats.json"))
        errors = np.load(io.BytesIO(z.read("error_array.npz")))
    return stats, errors


@pytest.mark.parametrize(
    "name, est", [("orb", "KITTI_00_ORB.txt"), ("sptam", "KITTI_00_SPTAM.txt")]
)
def test_saved_evo_ape_results(evo_dir: Path, name: str, est: str) -> None:
    """evo's saved APE zips (SE(3) alignment): statistics and the whole error array.

    The saved RPE zips (10 m, 2018) do not apply: evo 1.38 itself gives other numbers for them
    (rmse 0.2368 vs 0.2263 saved for ORB), because the path-delta pair rule changed since;
    RPE agreement with evo 1.38 is tested above.
    """
    ref_src, est_src = ev.load_pair(evo_dir / "KITTI_00_gt.txt", evo_dir / est, ev.EvalOptions())
    ape_stats, ape_err = _zip_stats(require(evo_dir / "res_files" / f"{name}_ape.zip"))
    ours = ev.ape_of(ev.prepare(ref_src, est_src, ev.EvalOptions(align="se3")), "trans")
    _assert_stats_equal(ours.stats, ape_stats)
    np.testing.assert_allclose(ours.errors, ape_err, rtol=1e-9)
