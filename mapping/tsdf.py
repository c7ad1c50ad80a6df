"""Sparse voxel-block TSDF fusion of depth maps (KinectFusion-style projective TSDF).

Storage: blocks of ``B^3`` voxels (B = 8 by default) allocated only where a depth map has seen a
surface (within the truncation band). Block coordinates are packed into int64 keys kept in a
sorted array, so lookup and allocation are vectorised (``np.searchsorted``), not a Python dict.
Per-block data live in pooled arrays indexed by slot: ``tsdf`` (normalised signed distance in
[-1, 1], positive in front of the surface), ``weight`` (float32, 0 = never observed),
``color_x256`` (RGB running average in 1/256 steps, uint16: de-integration divides by what is
left of the weight, so 8-bit colour would amplify its rounding) and ``color_weight`` (the
weight of the colour average alone: colour is fused only within half the truncation band, and
a depth map fused without colour must not dilute it). :meth:`TsdfVolume.colors_u8` reads
colours as uint8.

Voxel ``g = (i, j, k)`` (global integer index) sits at ``g * voxel_m`` in the world frame; it lives
in block ``b = floor(g / B)`` at local index ``g - b * B``, flattened as ``(x * B + y) * B + z``.

Integration is a weighted running average; de-integration subtracts the same observation again,
which is exact as long as weights are not clamped (``max_weight=None``). Loop corrections use it:
de-integrate a keyframe with its old pose, integrate it with the new one. A voxel whose weight
(or colour weight) an update leaves at or below ``MIN_WEIGHT`` is reset to unobserved (tsdf 1,
weight 0; colour 0 with colour weight 0) instead of dividing by what is left.

The update loop runs compiled with numba when it is installed (``mapping.tsdf_numba``, the
``fast`` extra, ~5x faster: BENCHMARKS.md), else as the vectorised numpy below;
``TsdfConfig.kernel`` picks one. Both do the same float32 arithmetic in the same order and
give the same volume bit for bit (tested).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MIN_WEIGHT = 1e-4
"""Weights at or below this after an update count as zero (one observation weighs 0.1-1)."""

_KEY_BITS = 21
_KEY_OFFSET = 1 << (_KEY_BITS - 1)
_KEY_MASK = (1 << _KEY_BITS) - 1


def pack_block_keys(block_xyz: np.ndarray) -> np.ndarray:
    """(N, 3) int block coordinates (|c| < 2^20) -> (N,) int64 keys, ordered lexicographically."""
    c = np.asarray(block_xyz, dtype=np.int64) + _KEY_OFFSET
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


def unpack_block_keys(keys: np.ndarray) -> np.ndarray:
    """(N,) int64 keys -> (N, 3) int64 block coordinates."""
    k = np.asarray(keys, dtype=np.int64)
    out = np.stack(
        [(k >> (2 * _KEY_BITS)) & _KEY_MASK, (k >> _KEY_BITS) & _KEY_MASK, k & _KEY_MASK], axis=1
    )
    return out - _KEY_OFFSET


@dataclass(frozen=True)
class TsdfConfig:
    """Parameters of a :class:`TsdfVolume`."""

    voxel_m: float = 0.02
    """Voxel edge length (m)."""
    truncation_m: float | None = None
    """Truncation distance (m); None = 4 voxels."""
    block_size: int = 8
    """Voxels per block edge."""
    min_depth_m: float = 0.1
    """Depth below this is ignored."""
    max_depth_m: float = 5.0
    """Depth beyond this is ignored."""
    allocation_stride: int = 4
    """Pixel stride of the subsampled depth used to find the blocks to allocate."""
    max_weight: float | None = None
    """Clamp of the per-voxel weight (None: no clamp, keeps de-integration exact)."""
    kernel: str = "auto"
    """Update loop: "numba" (compiled, the ``fast`` extra), "numpy", or "auto" (numba when it
    imports)."""
    threads: int = 1
    """Threads of the compiled update loop (blocks shared out; numpy: ignored)."""

    @property
    def trunc_m(self) -> float:
        return self.truncation_m if self.truncation_m is not None else 4.0 * self.voxel_m


@dataclass(frozen=True)
class IntegrationStats:
    """What one integration touched."""

    blocks_touched: int
    blocks_allocated: int
    voxels_updated: int


class TsdfVolume:
    """A sparse, growable TSDF over voxel blocks (see the module docstring)."""

    def __init__(
        self,
        config: TsdfConfig | None = None,
        initial_capacity: int = 1024,
        chunk_blocks: int = 128,
    ) -> None:
        self.config = config or TsdfConfig()
        self.chunk_blocks = chunk_blocks
        b = self.config.block_size
        self._nvox = b**3
        self._keys_sorted = np.zeros(0, dtype=np.int64)  # sorted block keys
        self._slots_sorted = np.zeros(0, dtype=np.int64)  # slot of each sorted key
        self._num_blocks = 0
        self._block_xyz = np.zeros((initial_capacity, 3), dtype=np.int64)
        self.tsdf = np.ones((initial_capacity, self._nvox), dtype=np.float32)
        self.weight = np.zeros((initial_capacity, self._nvox), dtype=np.float32)
        self.color_x256 = np.zeros((initial_capacity, self._nvox, 3), dtype=np.uint16)
        self.color_weight = np.zeros((initial_capacity, self._nvox), dtype=np.float32)
        g = np.arange(b)
        local = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
        self._local_m = (local * self.config.voxel_m).astype(np.float32)  # (B^3, 3)
        self._kernel = _load_kernel(self.config.kernel, self.config.threads)

    @property
    def kernel(self) -> str:
        """The update loop in use: "numba" or "numpy"."""
        return "numpy" if self._kernel is None else "numba"

    # --- block bookkeeping ---------------------------------------------------------------------
    @property
    def num_blocks(self) -> int:
        return self._num_blocks

    def block_coords(self) -> np.ndarray:
        """(N, 3) int64 block coordinates of every allocated block, in slot order."""
        return self._block_xyz[: self._num_blocks]

    def lookup(self, keys: np.ndarray) -> np.ndarray:
        """Slots of the given block keys, -1 where a block is not allocated."""
        keys = np.asarray(keys, dtype=np.int64)
        if len(self._keys_sorted) == 0:
            return np.full(len(keys), -1, dtype=np.int64)
        pos = np.searchsorted(self._keys_sorted, keys)
        pos_c = np.minimum(pos, len(self._keys_sorted) - 1)
        found = self._keys_sorted[pos_c] == keys
        return np.where(found, self._slots_sorted[pos_c], -1)

    def _allocate(self, keys: np.ndarray) -> tuple[np.ndarray, int]:
        """Slots for unique ``keys``, allocating missing blocks. Returns (slots, number new)."""
        slots = self.lookup(keys)
        missing = slots < 0
        n_new = int(missing.sum())
        if n_new:
            new_keys = keys[missing]
            start = self._num_blocks
            self._reserve(start + n_new)
            new_slots = np.arange(start, start + n_new, dtype=np.int64)
            self._block_xyz[start : start + n_new] = unpack_block_keys(new_keys)
            self._num_blocks += n_new
            all_keys = np.concatenate([self._keys_sorted, new_keys])
            all_slots = np.concatenate([self._slots_sorted, new_slots])
            order = np.argsort(all_keys, kind="stable")
            self._keys_sorted = all_keys[order]
            self._slots_sorted = all_slots[order]
            slots[missing] = new_slots
        return slots, n_new

    def _reserve(self, n: int) -> None:
        cap = len(self.tsdf)
        if n <= cap:
            return
        new_cap = max(n, 2 * cap)
        grow = new_cap - cap
        self._block_xyz = np.concatenate([self._block_xyz, np.zeros((grow, 3), np.int64)])
        self.tsdf = np.concatenate([self.tsdf, np.ones((grow, self._nvox), np.float32)])
        self.weight = np.concatenate([self.weight, np.zeros((grow, self._nvox), np.float32)])
        self.color_x256 = np.concatenate(
            [self.color_x256, np.zeros((grow, self._nvox, 3), np.uint16)]
        )
        self.color_weight = np.concatenate(
            [self.color_weight, np.zeros((grow, self._nvox), np.float32)]
        )

    # --- integration ---------------------------------------------------------------------------
    def _blocks_near_surface(
        self, depth_m: np.ndarray, K: np.ndarray, world_from_cam: np.ndarray
    ) -> np.ndarray:
        """Unique keys of the blocks within the truncation band of a (subsampled) depth map."""
        cfg = self.config
        s = max(1, int(cfg.allocation_stride))
        block_m = cfg.voxel_m * cfg.block_size
        trunc = cfg.trunc_m
        n_steps = max(2, int(np.ceil(2 * trunc / (0.5 * block_m))) + 1)
        if self._kernel is not None:
            from mapping.tsdf_numba import block_keys_near_surface

            found = block_keys_near_surface(
                depth_m,
                s,
                float(K[0, 0]),
                float(K[1, 1]),
                float(K[0, 2]),
                float(K[1, 2]),
                np.ascontiguousarray(world_from_cam[:3, :3], np.float64),
                np.ascontiguousarray(world_from_cam[:3, 3], np.float64),
                np.linspace(-trunc, trunc, n_steps),
                block_m,
                cfg.min_depth_m,
                cfg.max_depth_m,
            )
            return found  # sorted, unique
        d = np.nan_to_num(depth_m[::s, ::s].astype(np.float32), nan=0.0)
        v, u = np.nonzero((d > cfg.min_depth_m) & (d < cfg.max_depth_m))
        z = d[v, u].astype(np.float64)  # float64 as the compiled version: the same blocks
        x = (u * s - K[0, 2]) / K[0, 0]
        y = (v * s - K[1, 2]) / K[1, 1]
        rays = np.stack([x, y, np.ones_like(x)], axis=1)  # z = 1 rays
        offsets = np.linspace(-trunc, trunc, n_steps)
        rot = world_from_cam[:3, :3]
        origin = world_from_cam[:3, 3]
        keys: list[np.ndarray] = []
        for off in offsets:
            p_cam = rays * (z + off)[:, None]
            p_world = p_cam @ rot.T + origin
            blocks = np.floor(p_world / block_m).astype(np.int64)
            keys.append(np.unique(pack_block_keys(blocks)))
        return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)

    def integrate(
        self,
        depth_m: np.ndarray,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        color: np.ndarray | None = None,
        weight: float = 1.0,
        weight_map: np.ndarray | None = None,
    ) -> IntegrationStats:
        """Fuse one depth map (H, W) in metres (0 or NaN = invalid) seen from ``world_from_cam``.

        ``K`` is the 3x3 pinhole matrix of the (undistorted) depth image; ``color`` (H, W, 3)
        uint8 RGB registered to the depth. A negative ``weight`` removes an observation (see
        :meth:`deintegrate`). ``weight_map`` (H, W) multiplies ``weight`` per pixel (e.g. a depth
        uncertainty weight); pass the same map to de-integrate.
        """
        cfg = self.config
        depth = np.ascontiguousarray(depth_m, dtype=np.float32)
        h, w = depth.shape
        keys = self._blocks_near_surface(depth, K, world_from_cam)
        if weight > 0:
            slots, n_new = self._allocate(keys)
        else:  # de-integration never allocates
            slots = self.lookup(keys)
            slots = slots[slots >= 0]
            n_new = 0
        if len(slots) == 0:
            return IntegrationStats(0, 0, 0)
        slots = np.sort(slots)  # memory order of the voxel arrays
        cam_from_world = np.linalg.inv(world_from_cam)
        k_rot = (K @ cam_from_world[:3, :3]).astype(np.float32)
        k_trans = (K @ cam_from_world[:3, 3]).astype(np.float32)
        # Image-plane homogeneous coordinates K (R p + t) of every voxel, as the block's
        # origin term plus a local term. Written out elementwise (not a matrix product, whose
        # summation order BLAS picks by size) so both loops get the same float32 values.
        local = _times_k_rot(self._local_m, k_rot, np.zeros(3, np.float32))  # (B^3, 3)
        color_img = None if color is None else np.ascontiguousarray(color, dtype=np.uint8)
        if color_img is not None and color_img.shape[:2] != (h, w):
            raise ValueError(f"colour image {color_img.shape[:2]} differs from depth {(h, w)}")
        wmap = None if weight_map is None else np.ascontiguousarray(weight_map, np.float32)
        if wmap is not None and wmap.shape != (h, w):
            raise ValueError(f"weight map {wmap.shape} differs from depth {(h, w)}")
        if self._kernel is not None:
            from mapping.tsdf_numba import flat_depth_and_weight

            if self.config.threads > 1:
                import numba

                numba.set_num_threads(min(self.config.threads, numba.config.NUMBA_NUM_THREADS))  # type: ignore[attr-defined]
            depth_nb, weight_nb = flat_depth_and_weight(
                depth,
                cfg.min_depth_m,
                cfg.max_depth_m,
                np.zeros((0, 0), np.float32) if wmap is None else wmap,
            )
            n_upd = self._kernel(
                slots,
                self._block_origins_k(slots, k_rot, k_trans),
                np.ascontiguousarray(local.T),
                w,
                depth_nb,
                np.zeros(0, np.uint8) if color_img is None else color_img.reshape(-1),
                weight_nb,
                np.float32(weight),
                np.float32(cfg.trunc_m),
                np.float32(cfg.min_depth_m),
                np.float32(-1.0 if cfg.max_weight is None else cfg.max_weight),
                np.float32(MIN_WEIGHT),
                self.tsdf,
                self.weight,
                self.color_x256,
                self.color_weight,
            )
            return IntegrationStats(len(slots), n_new, int(n_upd))
        depth_flat = np.zeros(h * w + 1, dtype=np.float32)  # last entry: 0 for "outside"
        depth_flat[:-1] = np.nan_to_num(depth.ravel(), nan=0.0)
        depth_flat[(depth_flat < cfg.min_depth_m) | (depth_flat > cfg.max_depth_m)] = 0.0
        color_flat = None if color_img is None else color_img.reshape(-1, 3)
        weight_flat: np.ndarray | None = None
        if wmap is not None:
            weight_flat = np.zeros(h * w + 1, dtype=np.float32)
            weight_flat[:-1] = wmap.ravel()
        # Chunks of blocks keep every temporary in cache (~64k voxels): 2-3x faster than one pass.
        n_upd = 0
        for c0 in range(0, len(slots), self.chunk_blocks):
            chunk = slots[c0 : c0 + self.chunk_blocks]
            n_upd += self._integrate_blocks(
                chunk,
                self._block_origins_k(chunk, k_rot, k_trans),
                local,
                depth_flat,
                (h, w),
                color_flat,
                np.float32(weight),
                weight_flat,
            )
        return IntegrationStats(len(slots), n_new, n_upd)

    def _block_origins_k(self, slots: np.ndarray, k_rot: np.ndarray, k_trans: np.ndarray):
        """(Nb, 3) float32 K (R o + t) of the origins o of the given blocks."""
        block_m = self.config.voxel_m * self.config.block_size
        return _times_k_rot((self._block_xyz[slots] * block_m).astype(np.float32), k_rot, k_trans)

    def _integrate_blocks(
        self,
        slots: np.ndarray,
        origins: np.ndarray,
        local: np.ndarray,
        depth_flat: np.ndarray,
        hw: tuple[int, int],
        color_flat: np.ndarray | None,
        wgt: np.float32,
        weight_flat: np.ndarray | None = None,
    ) -> int:
        """The numpy update of the voxels of some blocks (``mapping.tsdf_numba`` is the same
        arithmetic as one compiled loop); returns the voxels updated."""
        cfg = self.config
        h, w = hw
        # origins (Nb, 3) and local (B^3, 3): see integrate().
        zc = origins[:, 2:3] + local[None, :, 2]  # (Nb, B^3) depth along the optical axis
        inv_z = np.float32(1.0) / np.maximum(zc, np.float32(cfg.min_depth_m))
        u = (origins[:, 0:1] + local[None, :, 0]) * inv_z
        u += np.float32(0.5)  # round to the nearest pixel centre
        v = (origins[:, 1:2] + local[None, :, 1]) * inv_z
        v += np.float32(0.5)
        ui = u.astype(np.int32)
        vi = v.astype(np.int32)
        # Negative indices become huge as uint32, so one comparison checks both bounds; u in
        # (-1, 0) truncates to 0, hence the sign tests.
        inside = (ui.view(np.uint32) < w) & (vi.view(np.uint32) < h) & (zc > cfg.min_depth_m)
        inside &= (u >= 0) & (v >= 0)
        pix = vi * np.int32(w) + ui
        pix[~inside] = h * w
        d = depth_flat[pix]
        sdf = d - zc
        trunc = np.float32(cfg.trunc_m)
        upd = (d > 0) & (sdf >= -trunc)
        # Arithmetic masking (no np.where: data-dependent selects are slow on big masks).
        inc = upd.astype(np.float32) * wgt
        if weight_flat is not None:
            inc *= weight_flat[pix]
        upd &= inc != 0
        n_upd = int(np.count_nonzero(upd))
        if n_upd == 0:
            return 0
        obs = np.minimum(sdf * (np.float32(1.0) / trunc), np.float32(1.0))
        w_old = self.weight[slots]
        t_old = self.tsdf[slots]
        w_new = w_old + inc
        gone = upd & (w_new <= MIN_WEIGHT)  # removed to nothing: back to unobserved
        denom = np.maximum(w_new, np.float32(MIN_WEIGHT))
        t_new = t_old + inc * (obs - t_old) / denom  # running mean; unchanged where inc == 0
        np.clip(t_new, -1.0, 1.0, out=t_new)
        t_new[gone] = 1.0
        w_new[gone] = 0.0
        if cfg.max_weight is not None:
            np.minimum(w_new, np.float32(cfg.max_weight), out=w_new)
        if color_flat is not None:
            # Colour only matters near the zero crossing: fused within half the band.
            near = upd & (np.abs(sdf) < np.float32(0.5) * trunc)
            bi, li = np.nonzero(near)
            sl = slots[bi]
            inc_n = inc[bi, li]
            cw_new = self.color_weight[sl, li] + inc_n
            c_gone = cw_new <= MIN_WEIGHT
            frac = inc_n / np.maximum(cw_new, np.float32(MIN_WEIGHT))
            c_obs = color_flat[pix[bi, li]].astype(np.float32) * np.float32(256.0)
            c_old = self.color_x256[sl, li].astype(np.float32)
            c_new = c_old + (c_obs - c_old) * frac[:, None] + np.float32(0.5)
            c_new[c_gone] = 0.0
            cw_new[c_gone] = 0.0
            if cfg.max_weight is not None:
                np.minimum(cw_new, np.float32(cfg.max_weight), out=cw_new)
            self.color_x256[sl, li] = np.clip(c_new, 0, 65535).astype(np.uint16)
            self.color_weight[sl, li] = cw_new
        self.tsdf[slots] = t_new
        self.weight[slots] = w_new
        return n_upd

    def deintegrate(
        self,
        depth_m: np.ndarray,
        K: np.ndarray,
        world_from_cam: np.ndarray,
        color: np.ndarray | None = None,
        weight_map: np.ndarray | None = None,
    ) -> IntegrationStats:
        """Remove a depth map integrated earlier with the same pose (exact without weight clamp)."""
        return self.integrate(depth_m, K, world_from_cam, color, weight=-1.0, weight_map=weight_map)

    def warm_up(self) -> None:
        """Load (or compile, once: numba caches it on disk) the update loop now, on a scratch
        volume of the same configuration, so the first real depth map does not wait ~1 s."""
        if self._kernel is None:
            return
        k = np.array([[50.0, 0.0, 16.0], [0.0, 50.0, 12.0], [0.0, 0.0, 1.0]])
        depth = np.full((24, 32), 1.0, np.float32)
        scratch = TsdfVolume(self.config, initial_capacity=8)
        scratch.integrate(
            depth, k, np.eye(4), np.zeros((24, 32, 3), np.uint8), weight_map=np.ones_like(depth)
        )

    # --- queries -------------------------------------------------------------------------------
    def voxel_positions(self, slots: np.ndarray | None = None) -> np.ndarray:
        """(N, B^3, 3) float64 world positions of the voxels of the given blocks (all by default)."""
        if slots is None:
            slots = np.arange(self._num_blocks)
        block_m = self.config.voxel_m * self.config.block_size
        origins = self._block_xyz[slots] * block_m
        return origins[:, None, :] + self._local_m[None, :, :].astype(np.float64)

    def surface_points(self, max_abs_tsdf: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
        """Voxels near the zero crossing: (N, 3) world positions and (N, 3) uint8 colours."""
        n = self._num_blocks
        near = (self.weight[:n] > 0) & (np.abs(self.tsdf[:n]) < max_abs_tsdf)
        bi, vi = np.nonzero(near)
        block_m = self.config.voxel_m * self.config.block_size
        pts = self._block_xyz[bi] * block_m + self._local_m[vi]
        return pts, self.colors_u8(bi, vi)

    def colors_u8(self, slots: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(N, 3) uint8 RGB of voxels (slot, local index); black where no colour was fused
        (see :meth:`has_color`)."""
        c = self.color_x256[slots, local].astype(np.float32) * np.float32(1.0 / 256.0)
        return np.clip(c + 0.5, 0, 255).astype(np.uint8)

    def has_color(self, slots: np.ndarray, local: np.ndarray) -> np.ndarray:
        """(N,) bool: colour was fused into these voxels (and not all removed again)."""
        return self.color_weight[slots, local] > 0

    def observed_voxel_count(self) -> int:
        return int((self.weight[: self._num_blocks] > 0).sum())

    def memory_bytes(self) -> int:
        n = self._num_blocks
        return int(
            self.tsdf[:n].nbytes
            + self.weight[:n].nbytes
            + self.color_x256[:n].nbytes
            + self.color_weight[:n].nbytes
        )


def _times_k_rot(p: np.ndarray, k_rot: np.ndarray, k_trans: np.ndarray) -> np.ndarray:
    """(N, 3) float32 ``k_rot @ p + k_trans`` per row, summed in a fixed order."""
    out = p[:, 0:1] * k_rot[:, 0] + p[:, 1:2] * k_rot[:, 1]
    out += p[:, 2:3] * k_rot[:, 2]
    out += k_trans
    return np.ascontiguousarray(out, dtype=np.float32)


def numba_available() -> bool:
    """True when the compiled update loop (numba, the ``fast`` extra) imports."""
    return _load_kernel("auto") is not None


def _load_kernel(name: str, threads: int = 1):  # noqa: ANN202 - a numba dispatcher or None
    """The compiled update loop for ``kernel`` "numba"/"auto", None for numpy."""
    if name == "numpy":
        return None
    if name not in ("auto", "numba"):
        raise ValueError(f"TSDF kernel {name!r}: use auto, numba or numpy")
    try:
        from mapping.tsdf_numba import integrate_blocks, integrate_blocks_parallel
    except ImportError:
        if name == "numba":
            raise
        return None
    return integrate_blocks_parallel if threads > 1 else integrate_blocks
