"""The TSDF integration loop compiled with numba (the optional ``fast`` extra).

The same arithmetic as the numpy loop in :mod:`mapping.tsdf`, operation for operation in
float32, so both give the same volume bit for bit (tested); what differs is how the work is
laid out. Per block of ``B^3`` voxels, four short passes over scratch arrays that stay in L1:

1. project: image-plane coordinates of every voxel as the block's projected origin (one
   (Nb, 3) table per frame, computed by the caller) plus a per-frame table of the local
   offsets (3, B^3), both already multiplied by ``K R``; the pixel index or a sentinel. No
   branches, so LLVM vectorises it.
2. gather the depth (and per-pixel weight) of those pixels.
3. the TSDF and weight update of every voxel, branch-free (a voxel that is not updated gets
   an increment of 0, which leaves it unchanged, as in the numpy loop): vectorised.
4. colour, only for the voxels near the surface, listed by a branch-free compaction.

Hand-written rather than a library call because the mapper needs de-integration (negative
weights) and per-pixel weights, which no installable TSDF library offers (BENCHMARKS.md
"Mapping": Open3D 0.20's legacy ``ScalableTSDFVolume`` integrates nothing, 0.19's works but
adds only positive, per-frame weights; its tensor ``VoxelBlockGrid`` was slower than this).

Importing this module raises ImportError without numba; :mod:`mapping.tsdf` then falls back.
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
    offsets around every ``stride``-th pixel's depth fall in, sorted and unique."""
    h, w = depth.shape
    n_max = ((h + stride - 1) // stride) * ((w + stride - 1) // stride) * offsets_m.shape[0]
    # Open-addressing hash set of the keys seen (keys are >= 0; -1 = empty): sorting every
    # sample instead cost 3x as much.
    bits = 10
    while (1 << bits) < 2 * n_max:
        bits += 1
    size = 1 << bits
    mask = np.int64(size - 1)
    table = np.full(size, -1, np.int64)
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
                if key == last:  # neighbouring samples mostly share a block
                    continue
                last = key
                slot = ((key * np.int64(-7046029254386353131)) >> np.int64(64 - bits)) & mask
                while table[slot] != -1 and table[slot] != key:
                    slot = (slot + 1) & mask
                if table[slot] == -1:  # at most n_max keys: the table never fills
                    table[slot] = key
                    out[n] = key
                    n += 1
    return np.sort(out[:n])


@njit(cache=True, nogil=True)
def flat_depth_and_weight(
    depth: np.ndarray,  # (H, W) float32 metres
    min_depth_m: float,
    max_depth_m: float,
    weight_map: np.ndarray,  # (H, W) float32, or (0, 0) for none
) -> tuple[np.ndarray, np.ndarray]:
    """(H W + 1,) depth with 0 where invalid (NaN, outside [min, max]) and 0 in the last
    entry (the pixel of voxels outside the image); the weight map flattened the same way, or
    (0,) without one. As the numpy loop prepares them."""
    h, w = depth.shape
    dmin = np.float32(min_depth_m)
    dmax = np.float32(max_depth_m)
    out = np.zeros(h * w + 1, np.float32)
    for v in range(h):
        for u in range(w):
            d = depth[v, u]
            if d >= dmin and d <= dmax:  # False for NaN
                out[v * w + u] = d
    if weight_map.shape[0] == 0:
        return out, np.zeros(0, np.float32)
    wf = np.zeros(h * w + 1, np.float32)
    for v in range(h):
        for u in range(w):
            wf[v * w + u] = weight_map[v, u]
    return out, wf


@njit(cache=True, nogil=True, error_model="numpy")
def _update_blocks(
    lo: int,
    hi: int,
    slots: np.ndarray,  # (Nb,) int64 block slots
    origins: np.ndarray,  # (Nb, 3) float32: K (R o + t) of each block's origin o
    local: np.ndarray,  # (3, B^3) float32: K R l of each local voxel offset l
    width: int,
    depth_flat: np.ndarray,  # (H W + 1,) float32, from flat_depth_and_weight
    color_flat: np.ndarray,  # (H W 3,) uint8 RGB, or (0,) for none
    weight_flat: np.ndarray,  # (H W + 1,) float32, or (0,) for none
    wgt: np.float32,  # weight of this observation (negative: de-integrate)
    trunc: np.float32,  # truncation distance, m
    zmin: np.float32,  # voxels nearer than this to the camera are skipped
    max_weight: np.float32,  # <= 0: no clamp
    min_weight: np.float32,  # a weight at or below this after an update counts as zero
    tsdf: np.ndarray,  # (capacity, B^3) float32, updated
    weight: np.ndarray,  # (capacity, B^3) float32, updated
    color_x256: np.ndarray,  # (capacity, B^3, 3) uint16, updated
    color_weight: np.ndarray,  # (capacity, B^3) float32, updated
) -> int:
    """Update the voxels of blocks ``slots[lo:hi]``; returns how many were updated."""
    nvox = local.shape[1]
    hw = depth_flat.shape[0] - 1
    h = hw // width
    has_color = color_flat.shape[0] > 0
    has_wmap = weight_flat.shape[0] > 0
    pix = np.empty(nvox, np.int32)
    zc_sdf = np.empty(nvox, np.float32)  # depth along the axis, then the signed distance
    dd = np.empty(nvox, np.float32)
    wv = np.ones(nvox, np.float32)
    incs = np.empty(nvox, np.float32)
    near_list = np.empty(nvox, np.int32)
    f0 = np.float32(0.0)
    f1 = np.float32(1.0)
    half = np.float32(0.5)
    f256 = np.float32(256.0)
    f65535 = np.float32(65535.0)
    fw = np.float32(width)
    fh = np.float32(h)
    inv_trunc = f1 / trunc
    neg_trunc = -trunc
    near = half * trunc
    clamp = max_weight > f0
    lx = local[0]
    ly = local[1]
    lz = local[2]
    n_upd = 0
    for bi in range(lo, hi):
        s = slots[bi]
        o0 = origins[bi, 0]
        o1 = origins[bi, 1]
        o2 = origins[bi, 2]
        # 1. project (rounded to the nearest pixel centre; hw = outside the image)
        for li in range(nvox):
            zc = o2 + lz[li]
            inv_z = f1 / max(zc, zmin)
            u = (o0 + lx[li]) * inv_z + half
            v = (o1 + ly[li]) * inv_z + half
            ui = np.int32(min(max(u, f0), fw))
            vi = np.int32(min(max(v, f0), fh))
            outside = (zc <= zmin) | (u < f0) | (v < f0) | (ui >= width) | (vi >= h)
            pix[li] = np.int32(hw) if outside else vi * np.int32(width) + ui
            zc_sdf[li] = zc
        # 2. gather
        for li in range(nvox):
            dd[li] = depth_flat[pix[li]]
        if has_wmap:
            for li in range(nvox):
                wv[li] = weight_flat[pix[li]]
        # 3. TSDF and weight (running mean; a voxel removed to nothing is reset)
        ts = tsdf[s]
        ws = weight[s]
        nu = 0
        for li in range(nvox):
            d = dd[li]
            sdf = d - zc_sdf[li]
            ok = (d > f0) & (sdf >= neg_trunc)
            inc = (f1 if ok else f0) * wgt * wv[li]
            upd = inc != f0
            obs = min(sdf * inv_trunc, f1)
            w_new = ws[li] + inc
            gone = upd & (w_new <= min_weight)
            t_old = ts[li]
            t_new = t_old + inc * (obs - t_old) / max(w_new, min_weight)
            t_new = min(max(t_new, -f1), f1)
            ts[li] = f1 if gone else t_new
            w_new = f0 if gone else w_new
            ws[li] = min(w_new, max_weight) if clamp else w_new
            nu += upd
            zc_sdf[li] = sdf
            incs[li] = inc
        n_upd += nu
        if not has_color:
            continue
        # 4. colour, within half the band of the surface
        nc = 0
        for li in range(nvox):
            near_list[nc] = li
            nc += (incs[li] != f0) & (abs(zc_sdf[li]) < near)
        cws = color_weight[s]
        cs = color_x256[s]
        for k in range(nc):
            li = near_list[k]
            inc = incs[li]
            cw_new = cws[li] + inc
            if cw_new <= min_weight:
                cws[li] = f0
                cs[li, 0] = 0
                cs[li, 1] = 0
                cs[li, 2] = 0
                continue
            frac = inc / cw_new
            q = 3 * pix[li]
            for c in range(3):
                c_old = np.float32(cs[li, c])
                c_obs = np.float32(color_flat[q + c]) * f256
                c_new = c_old + (c_obs - c_old) * frac + half
                cs[li, c] = np.uint16(min(max(c_new, f0), f65535))
            cws[li] = min(cw_new, max_weight) if clamp else cw_new
    return n_upd


@njit(cache=True, nogil=True)
def integrate_blocks(
    slots, origins, local, width, depth_flat, color_flat, weight_flat, wgt, trunc, zmin,
    max_weight, min_weight, tsdf, weight, color_x256, color_weight,
):  # fmt: skip
    """Every voxel of the blocks ``slots`` (the arguments as :func:`_update_blocks`), one
    thread; returns the voxels updated."""
    return _update_blocks(
        0, slots.shape[0], slots, origins, local, width, depth_flat, color_flat, weight_flat,
        wgt, trunc, zmin, max_weight, min_weight, tsdf, weight, color_x256, color_weight,
    )  # fmt: skip


@njit(cache=True, nogil=True, parallel=True)
def integrate_blocks_parallel(
    slots, origins, local, width, depth_flat, color_flat, weight_flat, wgt, trunc, zmin,
    max_weight, min_weight, tsdf, weight, color_x256, color_weight,
):  # fmt: skip
    """The same, runs of blocks shared out over numba's threads (distinct blocks share no
    voxel, so the result does not depend on the threads)."""
    n = slots.shape[0]
    n_chunks = min(n, 64)
    counts = np.zeros(n_chunks, np.int64)
    for c in prange(n_chunks):
        counts[c] = _update_blocks(
            c * n // n_chunks, (c + 1) * n // n_chunks, slots, origins, local, width,
            depth_flat, color_flat, weight_flat, wgt, trunc, zmin, max_weight, min_weight,
            tsdf, weight, color_x256, color_weight,
        )  # fmt: skip
    return counts.sum()
