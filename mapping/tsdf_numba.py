"""The TSDF integration loop compiled with numba (the optional ``fast`` extra).

One pass over the voxels of the touched blocks, each projected into the depth map and updated
in place: the numpy version in :mod:`mapping.tsdf` needs ~40 passes over (blocks x B^3)
temporaries for the same work (7-Scenes 640x480 at 1 cm: see BENCHMARKS.md "Mapping"). The
arithmetic is the numpy version's, step for step, so both give the same volume (tested).

Importing this module raises ImportError without numba; :mod:`mapping.tsdf` then falls back.
Why not Open3D (a well-kept library): 0.20's legacy ``ScalableTSDFVolume`` integrates nothing
in the ``open3d-cpu`` wheel here, and its tensor ``VoxelBlockGrid`` was slower than this loop
and has neither de-integration nor per-pixel weights, which loop corrections and stereo
depth need (BENCHMARKS.md "Mapping").

Each compiled function has its own name: numba's on-disk cache is keyed by it (two
dispatchers of one Python function overwrite each other's cache and recompile in every
process, 30 s for the parallel one under load).
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

_KEY_BITS = 21  # as mapping.tsdf.pack_block_keys
_KEY_OFFSET = 1 << (_KEY_BITS - 1)


@njit(cache=True, nogil=True)
def block_keys_near_surface(
    depth: np.ndarray,  # (H, W) float32 metres, NaN/0 = invalid
    stride: int,
    fx: float,
    fy: float,
    cx: float,
    cy: float,
    rot: np.ndarray,  # (3, 3) float64 world_from_cam rotation
    origin: np.ndarray,  # (3,) float64
    offsets_m: np.ndarray,  # (S,) float64 steps along each ray through the band
    block_m: float,
    min_depth_m: float,
    max_depth_m: float,
) -> np.ndarray:
    """Packed keys (``mapping.tsdf.pack_block_keys``) of the blocks that points at the given
    offsets around every ``stride``-th pixel's depth fall in; repeats of the previous key are
    left out (neighbouring samples mostly share a block), the caller makes them unique."""
    h, w = depth.shape
    n_max = ((h + stride - 1) // stride) * ((w + stride - 1) // stride) * offsets_m.shape[0]
    out = np.empty(n_max, np.int64)
    n = 0
    last = np.int64(-1)
    for v in range(0, h, stride):
        y = (v - cy) / fy
        for u in range(0, w, stride):
            z = depth[v, u]
            if not (z > min_depth_m and z < max_depth_m):
                continue
            x = (u - cx) / fx
            for k in range(offsets_m.shape[0]):
                zz = z + offsets_m[k]
                px, py = x * zz, y * zz
                key = np.int64(0)
                for r in range(3):
                    p = rot[r, 0] * px + rot[r, 1] * py + rot[r, 2] * zz + origin[r]
                    b = np.int64(np.floor(p / block_m)) + _KEY_OFFSET
                    key = (key << _KEY_BITS) | b
                if key != last:
                    out[n] = key
                    n += 1
                    last = key
    return out[:n]


@njit(cache=True, nogil=True)
def _update_block(
    s: int,  # the block's slot
    block_xyz: np.ndarray,  # (capacity, 3) int64
    block_size: int,
    voxel_m: float,
    k_rot: np.ndarray,  # (3, 3) float32: K @ cam_from_world rotation
    k_trans: np.ndarray,  # (3,) float32
    depth: np.ndarray,  # (H, W) float32 metres; outside [min, max] or NaN = invalid
    color: np.ndarray,  # (H, W, 3) uint8, or (0, 0, 3) for none
    weight_map: np.ndarray,  # (H, W) float32, or (0, 0) for none
    wgt: float,
    trunc_m: float,
    min_depth_m: float,
    max_depth_m: float,
    max_weight: float,  # <= 0: no clamp
    min_weight: float,  # a weight at or below this after an update counts as zero
    tsdf: np.ndarray,  # (capacity, B^3) float32, updated
    weight: np.ndarray,  # (capacity, B^3) float32, updated
    color_x256: np.ndarray,  # (capacity, B^3, 3) uint16, updated
    color_weight: np.ndarray,  # (capacity, B^3) float32, updated
) -> int:
    """Update every voxel of one block from one depth map (see ``mapping.tsdf``); returns how
    many were updated. Voxel (x, y, z) of a block is local index (x B + y) B + z."""
    h, w = depth.shape
    has_color = color.shape[0] > 0
    has_wmap = weight_map.shape[0] > 0
    bs = block_size
    f1 = np.float32(1.0)
    half = np.float32(0.5)
    inv_trunc = f1 / np.float32(trunc_m)
    trunc = np.float32(trunc_m)
    near = half * trunc
    zmin = np.float32(min_depth_m)
    dmin = np.float32(min_depth_m)
    dmax = np.float32(max_depth_m)
    block_m = voxel_m * bs
    n_upd = 0
    ox = block_xyz[s, 0] * block_m
    oy = block_xyz[s, 1] * block_m
    oz = block_xyz[s, 2] * block_m
    for x in range(bs):
        px = np.float32(ox + x * voxel_m)
        for y in range(bs):
            py = np.float32(oy + y * voxel_m)
            a0 = k_rot[0, 0] * px + k_rot[0, 1] * py + k_trans[0]
            a1 = k_rot[1, 0] * px + k_rot[1, 1] * py + k_trans[1]
            a2 = k_rot[2, 0] * px + k_rot[2, 1] * py + k_trans[2]
            base = (x * bs + y) * bs
            for z in range(bs):
                pz = np.float32(oz + z * voxel_m)
                zc = a2 + k_rot[2, 2] * pz
                if not zc > zmin:
                    continue
                inv_z = f1 / zc
                u = (a0 + k_rot[0, 2] * pz) * inv_z + half  # nearest pixel centre
                v = (a1 + k_rot[1, 2] * pz) * inv_z + half
                if not (u >= 0 and v >= 0 and u < w and v < h):
                    continue
                ui = int(u)
                vi = int(v)
                d = depth[vi, ui]
                if not (d >= dmin and d <= dmax):
                    continue
                sdf = d - zc
                if sdf < -trunc:
                    continue
                inc = np.float32(wgt)
                if has_wmap:
                    inc *= weight_map[vi, ui]
                if inc == 0:
                    continue
                n_upd += 1
                li = base + z
                obs = min(sdf * inv_trunc, f1)
                w_new = weight[s, li] + inc
                if w_new <= min_weight:  # removed to nothing: back to unobserved
                    tsdf[s, li] = f1
                    weight[s, li] = 0
                else:
                    t_old = tsdf[s, li]
                    t_new = t_old + inc * (obs - t_old) / w_new
                    tsdf[s, li] = min(max(t_new, -f1), f1)
                    if max_weight > 0 and w_new > max_weight:
                        w_new = np.float32(max_weight)
                    weight[s, li] = w_new
                if has_color and abs(sdf) < near:
                    cw_new = color_weight[s, li] + inc
                    if cw_new <= min_weight:
                        color_weight[s, li] = 0
                        for c in range(3):
                            color_x256[s, li, c] = 0
                    else:
                        frac = inc / cw_new
                        for c in range(3):
                            c_old = np.float32(color_x256[s, li, c])
                            c_obs = np.float32(color[vi, ui, c]) * np.float32(256.0)
                            c_new = c_old + (c_obs - c_old) * frac + half
                            color_x256[s, li, c] = np.uint16(min(max(c_new, 0.0), 65535.0))
                        if max_weight > 0 and cw_new > max_weight:
                            cw_new = np.float32(max_weight)
                        color_weight[s, li] = cw_new
    return n_upd


@njit(cache=True, nogil=True)
def integrate_blocks(
    slots, block_xyz, block_size, voxel_m, k_rot, k_trans, depth, color, weight_map, wgt,
    trunc_m, min_depth_m, max_depth_m, max_weight, min_weight, tsdf, weight, color_x256,
    color_weight,
):  # fmt: skip
    """Every voxel of the blocks ``slots`` ((Nb,) int64; the other arguments as
    :func:`_update_block`), one thread."""
    n = 0
    for bi in range(slots.shape[0]):
        n += _update_block(
            slots[bi], block_xyz, block_size, voxel_m, k_rot, k_trans, depth, color,
            weight_map, wgt, trunc_m, min_depth_m, max_depth_m, max_weight, min_weight, tsdf,
            weight, color_x256, color_weight,
        )  # fmt: skip
    return n


@njit(cache=True, nogil=True, parallel=True)
def integrate_blocks_parallel(
    slots, block_xyz, block_size, voxel_m, k_rot, k_trans, depth, color, weight_map, wgt,
    trunc_m, min_depth_m, max_depth_m, max_weight, min_weight, tsdf, weight, color_x256,
    color_weight,
):  # fmt: skip
    """The same, blocks shared out over numba's threads (distinct blocks share no voxel)."""
    n = 0
    for bi in prange(slots.shape[0]):
        n += _update_block(
            slots[bi], block_xyz, block_size, voxel_m, k_rot, k_trans, depth, color,
            weight_map, wgt, trunc_m, min_depth_m, max_depth_m, max_weight, min_weight, tsdf,
            weight, color_x256, color_weight,
        )  # fmt: skip
    return n
