"""`slam fuse`: a dense mesh from an RGB-D folder, or from a sequence + trajectory (plane sweep)."""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Fuse depth maps into a sparse voxel-block TSDF and write its marching-cubes mesh as binary PLY
(vertex colours + normals; MeshLab, Open3D and Blender open it).

Two inputs:
  * an RGB-D folder in the Microsoft 7-Scenes layout (frame-XXXXXX.color.jpg, .depth.png in mm
    with 0 = invalid, .pose.txt = 4x4 world_from_camera, optional camera-intrinsics.txt;
    default fx = fy = 585, cx = 320, cy = 240): its sensor depth is fused with its poses.
    The colour camera is not the depth camera: its calibration is estimated from the frames
    (once per folder, cached in ~/.cache/pyvislam/rgbd_calibration) and every colour image is
    registered to its depth before fusion; the mesh's colour error against the registered
    colour images is printed (--no-register-color: fuse the raw colour, to compare);
  * any sequence `slam info` can read (MCAP, ROS 2 bag, EuRoC/TUM-VI folder) plus a
    trajectory (TUM: t x y z qx qy qz qw, world_from_body; default: the sequence's ground
    truth): every N-th frame gets a plane-sweep depth map (stereo partner + the nearest earlier
    keyframe), which is then fused.

Examples:
  slam fuse ../shared/data/7scenes_rgbd_400 --out kitchen.ply --voxel 0.02 --every 2
  slam fuse ../shared/data/7scenes_rgbd_400 --out raw.ply --every 2 --no-register-color
  slam fuse room.mcap --out room.ply --every 10                 # synthetic: ground-truth poses
  slam fuse V1_01_easy --trajectory run1/trajectory.tum --out v101.ply --depth-max 6
  slam fuse room.mcap --out room.ply --points room_points.ply --poisson room_poisson.ply
"""


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "fuse",
        help="TSDF-fuse depth (RGB-D folder, or plane sweep on a sequence) into a mesh",
        description=DESCRIPTION,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("input", type=Path, help="7-Scenes-style RGB-D folder, or a sequence")
    p.add_argument("--out", type=Path, required=True, help="output mesh .ply")
    p.add_argument("--voxel", type=float, default=0.02, help="voxel size in m (default 0.02)")
    p.add_argument(
        "--trajectory",
        type=Path,
        help="poses (TUM/EuRoC csv, world_from_body; RGB-D: world_from_camera at 30 Hz times)",
    )
    p.add_argument(
        "--every", type=int, default=None, help="use every N-th frame (RGB-D 1, else 10)"
    )
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many frames")
    p.add_argument("--depth-min", type=float, default=0.4, help="nearest sweep plane, m")
    p.add_argument("--depth-max", type=float, default=5.0, help="farthest depth used, m")
    p.add_argument("--planes", type=int, default=64, help="plane-sweep planes (default 64)")
    p.add_argument(
        "--no-register-color",
        action="store_true",
        help="RGB-D: fuse the colour image as if the depth camera took it (no registration)",
    )
    p.add_argument(
        "--color-error-frames",
        type=int,
        default=20,
        help="RGB-D: frames the mesh colour error is measured on (default 20; 0: none)",
    )
    p.add_argument("--points", type=Path, help="also write the surface voxels as a point cloud")
    p.add_argument(
        "--poisson", type=Path, help="also write a Poisson surface (needs the optional open3d)"
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from mapping.fuse import fuse_rgbd_folder, fuse_sequence
    from mapping.mapper import MapperConfig
    from mapping.planesweep import SweepConfig
    from mapping.tsdf import TsdfConfig
    from slam.core.errors import InputError

    if args.voxel <= 0 or args.voxel > 1.0:
        raise InputError(f"--voxel {args.voxel}: give a voxel size in metres, e.g. 0.02")
    trajectory = None
    if args.trajectory is not None:
        from slam.evaluation.io import read_trajectory

        trajectory = read_trajectory(args.trajectory).trajectory
    config = MapperConfig(
        tsdf=TsdfConfig(voxel_m=args.voxel, max_depth_m=args.depth_max, threads=2),
        sweep=SweepConfig(
            depth_min_m=args.depth_min,
            depth_max_m=max(args.depth_max * 1.5, args.depth_min * 2),
            num_planes=args.planes,
        ),
    )
    is_rgbd = args.input.is_dir() and (
        any(args.input.glob("frame-*.depth.png")) or any(args.input.glob("data/frame-*.depth.png"))
    )
    if is_rgbd:
        # Sensor depth: every frame counts (no motion gate), every observed surface is meshed.
        config = MapperConfig(
            tsdf=config.tsdf, mesh_min_weight=0.0, min_motion_m=0.0, min_motion_deg=0.0
        )
        result = fuse_rgbd_folder(
            args.input,
            config,
            args.every or 1,
            args.max_frames,
            trajectory,
            register_color=not args.no_register_color,
            color_error_frames=max(0, args.color_error_frames),
        )
    else:
        result = fuse_sequence(args.input, trajectory, config, args.every or 10, args.max_frames)
    if result.mesh.num_faces == 0:
        raise InputError(
            f"{args.input}: the fused volume holds no surface; check poses and --depth-max"
        )
    result.mesh.write_ply(str(args.out))
    print(result.summary())
    print(f"wrote {args.out}")
    if args.points is not None:
        from datasets.ply import write_ply_points

        pts, cols = result.mapper.volume.surface_points()
        write_ply_points(args.points, pts, cols)
        print(f"wrote {args.points} ({len(pts)} points)")
    if args.poisson is not None:
        from mapping.mesh import poisson_mesh

        m = result.mesh
        poisson = poisson_mesh(m.vertices_m, m.normals, m.colors_rgb)
        poisson.write_ply(str(args.poisson))
        print(f"wrote {args.poisson} (Poisson: {poisson.num_vertices} vertices)")
    return 0
