"""Surfaces from a TSDF: marching cubes over voxel blocks, and Poisson (optional, Open3D).

Marching cubes runs in scikit-image over many blocks at once: every block is gathered with its
+x/+y/+z neighbours' first voxel layer into a ``(B+1)^3`` lattice (so there are no seams between
blocks), the lattices are stacked along one axis and one ``marching_cubes`` call with a ``mask``
processes them all. A cube is only meshed if all 8 corners were observed, which also keeps
cubes that straddle two stacked blocks out. Vertices that neighbouring blocks both produce are
merged by their lattice edge, so the result is one connected, indexed mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from skimage.measure import marching_cubes

from datasets.ply import write_ply_mesh, write_ply_points
from mapping.tsdf import TsdfVolume, pack_block_keys

__all__ = [
    "TriangleMesh",
    "extract_mesh",
    "poisson_mesh",
    "remove_small_components",
    "vertex_normals",
    "write_ply_mesh",
    "write_ply_points",
]


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """An indexed triangle mesh in the world frame (metres)."""

    vertices_m: np.ndarray  # (N, 3) float32
    faces: np.ndarray  # (M, 3) int32, counter-clockwise seen from the free-space side
    normals: np.ndarray  # (N, 3) float32 unit, pointing to free space (towards the cameras)
    colors_rgb: np.ndarray | None = None  # (N, 3) uint8

    @property
    def num_vertices(self) -> int:
        return len(self.vertices_m)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        return self.vertices_m.min(axis=0), self.vertices_m.max(axis=0)

    def write_ply(self, path: str) -> None:
        write_ply_mesh(path, self.vertices_m, self.faces, self.normals, self.colors_rgb)

    @staticmethod
    def empty() -> TriangleMesh:
        return TriangleMesh(
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.int32),
            np.zeros((0, 3), np.float32),
            np.zeros((0, 3), np.uint8),
        )


def remove_small_components(mesh: TriangleMesh, min_vertices: int) -> TriangleMesh:
    """The mesh without its connected pieces (vertices joined by face edges) of fewer than
    ``min_vertices`` vertices: the speckle that single noisy depth maps leave, mostly far from
    any surface. ``min_vertices`` <= 1 returns the mesh unchanged."""
    n = mesh.num_vertices
    if min_vertices <= 1 or n == 0:
        return mesh
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = mesh.faces.astype(np.int64)
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(edges), np.int8), (edges[:, 0], edges[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    keep = np.bincount(label)[label] >= min_vertices
    if keep.all():
        return mesh
    new_index = np.cumsum(keep) - 1
    faces = new_index[f[keep[f[:, 0]]]].astype(np.int32)  # a face's vertices share one label
    colors = None if mesh.colors_rgb is None else mesh.colors_rgb[keep]
    return TriangleMesh(mesh.vertices_m[keep], faces, mesh.normals[keep], colors)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit) from counter-clockwise faces."""
    v = vertices.astype(np.float64)
    f = faces.astype(np.int64)
    face_n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    out = np.zeros_like(v)
    for k in range(3):
        np.add.at(out, f[:, k], face_n)
    norm = np.linalg.norm(out, axis=1, keepdims=True)
    return (out / np.maximum(norm, 1e-12)).astype(np.float32)


def _lattice_tables(b: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For the (b+1)^3 lattice of a block: neighbour-block offset id (0..7), local flat index,
    and the 8 neighbour offsets."""
    g = np.arange(b + 1)
    lx, ly, lz = (a.ravel() for a in np.meshgrid(g, g, g, indexing="ij"))
    ox, oy, oz = lx // b, ly // b, lz // b  # 1 where the lattice point is in the next block
    offset_id = (ox * 4 + oy * 2 + oz).astype(np.int64)
    local = (((lx % b) * b + (ly % b)) * b + (lz % b)).astype(np.int64)
    offsets = np.array([[i >> 2 & 1, i >> 1 & 1, i & 1] for i in range(8)], dtype=np.int64)
    return offset_id, local, offsets


def extract_mesh(
    volume: TsdfVolume, min_weight: float = 0.0, batch_blocks: int = 2048
) -> TriangleMesh:
    """Marching cubes at the zero level of a TSDF (only cubes whose 8 corners have weight >
    ``min_weight``). Vertex colours: see ``_vertex_colors``."""
    cfg = volume.config
    b = cfg.block_size
    n_blocks = volume.num_blocks
    if n_blocks == 0:
        return TriangleMesh.empty()
    offset_id, local, offsets = _lattice_tables(b)
    blocks = volume.block_coords()
    lat = b + 1
    verts_all: list[np.ndarray] = []
    faces_all: list[np.ndarray] = []
    n_verts = 0
    for s0 in range(0, n_blocks, batch_blocks):
        bxyz = blocks[s0 : s0 + batch_blocks]
        nb = len(bxyz)
        neigh_keys = pack_block_keys((bxyz[:, None, :] + offsets[None]).reshape(-1, 3))
        neigh_slots = volume.lookup(neigh_keys).reshape(nb, 8)
        slot = neigh_slots[:, offset_id]  # (nb, lat^3)
        have = slot >= 0
        sl = np.where(have, slot, 0)
        tsdf = np.where(have, volume.tsdf[sl, local[None, :]], 1.0).astype(np.float32)
        seen = have & (volume.weight[sl, local[None, :]] > min_weight)
        tsdf = tsdf.reshape(nb, lat, lat, lat)
        seen = seen.reshape(nb, lat, lat, lat)
        # skimage processes the cube (x..x+1, y..y+1, z..z+1) iff mask[x+1, y+1, z+1].
        cube_ok = np.zeros_like(seen)
        c = seen[:, :-1, :-1, :-1] & seen[:, 1:, :-1, :-1] & seen[:, :-1, 1:, :-1]
        c &= seen[:, :-1, :-1, 1:] & seen[:, 1:, 1:, :-1] & seen[:, 1:, :-1, 1:]
        c &= seen[:, :-1, 1:, 1:] & seen[:, 1:, 1:, 1:]
        cube_ok[:, 1:, 1:, 1:] = c
        if not cube_ok.any():
            continue
        vol = tsdf.reshape(nb * lat, lat, lat)
        mask = cube_ok.reshape(nb * lat, lat, lat)
        if not (vol[mask].min() < 0 < vol[mask].max()):
            continue
        try:
            # Default "descent": faces wind counter-clockwise seen from the positive (free) side.
            v, f, _, _ = marching_cubes(vol, 0.0, mask=mask)
        except (RuntimeError, ValueError):  # no crossing inside the masked cubes
            continue
        blk = np.floor(v[:, 0] / lat).astype(np.int64)
        v_local = v.astype(np.float64)
        v_local[:, 0] -= blk * lat
        verts_all.append(bxyz[blk] * b + v_local)  # global lattice coordinates (voxel units)
        faces_all.append(f.astype(np.int64) + n_verts)
        n_verts += len(v)
    if not verts_all:
        return TriangleMesh.empty()
    verts_vox = np.concatenate(verts_all)
    faces = np.concatenate(faces_all)
    verts_vox, faces = _merge_duplicate_vertices(verts_vox, faces)
    vertices_m = (verts_vox * cfg.voxel_m).astype(np.float32)
    normals = vertex_normals(vertices_m, faces)
    colors = _vertex_colors(volume, verts_vox, faces)
    return TriangleMesh(vertices_m, faces.astype(np.int32), normals, colors)


def _merge_duplicate_vertices(
    verts_vox: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices that lie on the same lattice edge; drop degenerate faces."""
    base = np.floor(verts_vox + 1e-6).astype(np.int64)
    frac = verts_vox - base
    axis = np.argmax(frac, axis=1).astype(np.int64)  # the edge direction (any for a corner)
    axis[frac.max(axis=1) < 1e-6] = 3
    base -= base.min(axis=0)
    key = ((base[:, 0] << 20 | base[:, 1]) << 20 | base[:, 2]) << 2 | np.minimum(axis, 3)
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    faces = inverse.reshape(-1)[faces]
    good = (
        (faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 0] != faces[:, 2])
    )
    return verts_vox[first], faces[good]


def _vertex_colors(volume: TsdfVolume, verts_vox: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Vertex colours: a vertex lies on the lattice edge between two voxels; its colour is
    theirs, interpolated by position, over those that hold fused colour. A vertex whose two
    voxels hold none (observed only without colour, e.g. geometry-only re-integration) takes
    the mean of its coloured mesh neighbours (repeatedly, so colour flows into small holes);
    what no colour reaches stays mid-grey, never black."""
    b = volume.config.block_size
    base = np.floor(verts_vox + 1e-6).astype(np.int64)
    frac = np.clip(verts_vox - base, 0.0, 1.0)
    axis = np.argmax(frac, axis=1)
    t = frac[np.arange(len(frac)), axis]
    ends = [base, base.copy()]
    ends[1][np.arange(len(base)), axis] += 1
    acc = np.zeros((len(verts_vox), 3), np.float64)
    wsum = np.zeros(len(verts_vox), np.float64)
    for g, wt in zip(ends, (1.0 - t, t)):
        blk = np.floor_divide(g, b)
        loc = g - blk * b
        slots = volume.lookup(pack_block_keys(blk))
        flat = (loc[:, 0] * b + loc[:, 1]) * b + loc[:, 2]
        sl = np.maximum(slots, 0)
        ok = (slots >= 0) & volume.has_color(sl, flat)
        wv = np.where(ok, wt + 1e-6, 0.0)  # a vertex on a voxel still counts its neighbour
        acc += wv[:, None] * volume.colors_u8(sl, flat)
        wsum += wv
    colored = wsum > 0
    acc[colored] /= wsum[colored, None]
    if not colored.all() and colored.any() and len(faces):
        f = faces.astype(np.int64)
        src = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
        dst = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
        for _ in range(8):
            todo = ~colored
            if not todo.any():
                break
            use = colored[src] & todo[dst]
            if not use.any():
                break
            csum = np.zeros((len(acc), 3))
            cnt = np.zeros(len(acc))
            np.add.at(csum, dst[use], acc[src[use]])
            np.add.at(cnt, dst[use], 1.0)
            newly = cnt > 0
            acc[newly] = csum[newly] / cnt[newly, None]
            colored |= newly
    acc[~colored] = 128.0
    return np.clip(acc + 0.5, 0, 255).astype(np.uint8)


def poisson_available() -> bool:
    """True when the optional Open3D package is importable."""
    try:
        import open3d  # noqa: F401
    except ImportError:
        return False
    return True


def poisson_mesh(
    points: np.ndarray,
    normals: np.ndarray,
    colors_rgb: np.ndarray | None = None,
    depth: int = 9,
    density_quantile: float = 0.02,
) -> TriangleMesh:
    """Screened Poisson surface from oriented points via Open3D (an optional dependency).

    Vertices whose Poisson density is in the lowest ``density_quantile`` (the membrane Poisson
    spans over unobserved space) are removed.
    """
    try:
        import open3d as o3d
    except ImportError as exc:
        from slam.core.errors import SlamError

        raise SlamError(
            "Poisson reconstruction needs the optional package open3d: "
            "pip install open3d-cpu (Linux may also need libusb-1.0-0)"
        ) from exc
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(points, np.float64)))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    if colors_rgb is not None:
        pcd.colors = o3d.utility.Vector3dVector(np.asarray(colors_rgb, np.float64) / 255.0)
    mesh, densities = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(pcd, depth=depth)
    dens = np.asarray(densities)
    if len(dens) and density_quantile > 0:
        mesh.remove_vertices_by_mask(dens < np.quantile(dens, density_quantile))
    mesh.compute_vertex_normals()
    verts = np.asarray(mesh.vertices, dtype=np.float32)
    cols = (
        (np.asarray(mesh.vertex_colors) * 255).round().astype(np.uint8)
        if mesh.has_vertex_colors()
        else None
    )
    return TriangleMesh(
        verts,
        np.asarray(mesh.triangles, dtype=np.int32),
        np.asarray(mesh.vertex_normals, dtype=np.float32),
        cols,
    )
