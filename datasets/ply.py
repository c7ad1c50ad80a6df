"""Binary PLY (little endian) export and import of meshes and point clouds: the project's one
PLY module (the dense mapper's meshes, ``slam fuse`` point clouds, ``slam synth``'s scene mesh).

The writer emits what MeshLab, Open3D and Blender read: ``vertex`` with float x/y/z, optional
float nx/ny/nz and uchar red/green/blue, and ``face`` as ``list uchar int vertex_indices``.
Files are written atomically (temporary file in the same folder, then ``os.replace``).
The reader handles binary little-endian and ASCII files with scalar vertex properties and one
face list; it exists for tests and round trips, not as a general PLY library.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from slam.core.atomic import atomic_output
from slam.core.errors import InputError

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}


@dataclass(frozen=True, eq=False)
class PlyData:
    """Contents of a PLY file: vertex properties by name, faces (M, 3) or None, the header."""

    vertex: dict[str, np.ndarray]
    faces: np.ndarray | None
    header: str

    @property
    def points(self) -> np.ndarray:
        return np.stack([self.vertex["x"], self.vertex["y"], self.vertex["z"]], axis=1)


def _vertex_record(
    points: np.ndarray, normals: np.ndarray | None, colors_rgb: np.ndarray | None
) -> tuple[np.ndarray, list[str]]:
    points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    n = len(points)
    fields: list[tuple[str, str]] = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    header = ["property float x", "property float y", "property float z"]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
        header += ["property float nx", "property float ny", "property float nz"]
    if colors_rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        header += ["property uchar red", "property uchar green", "property uchar blue"]
    rec = np.empty(n, dtype=np.dtype(fields))
    rec["x"], rec["y"], rec["z"] = points[:, 0], points[:, 1], points[:, 2]
    if normals is not None:
        nrm = np.asarray(normals, dtype=np.float32).reshape(n, 3)
        rec["nx"], rec["ny"], rec["nz"] = nrm[:, 0], nrm[:, 1], nrm[:, 2]
    if colors_rgb is not None:
        col = np.asarray(colors_rgb).reshape(n, 3)
        if col.dtype != np.uint8:
            col = np.clip(np.round(col * 255 if col.max(initial=0) <= 1.0 else col), 0, 255)
        col = col.astype(np.uint8)
        rec["red"], rec["green"], rec["blue"] = col[:, 0], col[:, 1], col[:, 2]
    return rec, header


def _write_atomic(path: str | os.PathLike[str], header: str, chunks: list[bytes]) -> Path:
    path = Path(path)
    with atomic_output(path) as fh:
        fh.write(header.encode("ascii"))
        for chunk in chunks:
            fh.write(chunk)
    return path


def write_ply_points(
    path: str | os.PathLike[str],
    points: np.ndarray,
    colors_rgb: np.ndarray | None = None,
    normals: np.ndarray | None = None,
) -> Path:
    """Write a binary PLY point cloud (N, 3) with optional uint8 RGB colours and normals."""
    rec, props = _vertex_record(points, normals, colors_rgb)
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", "comment pyvislam point cloud"]
        + [f"element vertex {len(rec)}"]
        + props
        + ["end_header", ""]
    )
    return _write_atomic(path, header, [rec.tobytes()])


def write_ply_mesh(
    path: str | os.PathLike[str],
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray | None = None,
    colors_rgb: np.ndarray | None = None,
    *,
    comment: str = "pyvislam TSDF mesh",
) -> Path:
    """Write a binary PLY triangle mesh: vertices (N, 3), faces (M, 3) int, normals, colours.

    ``comment`` goes into the header (one line of text)."""
    if "\n" in comment or "\r" in comment:
        raise ValueError("a PLY comment is one line")
    rec, props = _vertex_record(vertices, normals, colors_rgb)
    tri = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if len(tri) and (tri.min() < 0 or tri.max() >= len(rec)):
        raise ValueError("face indices out of range")
    face_rec = np.empty(len(tri), dtype=np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
    face_rec["n"] = 3
    face_rec["v"] = tri.astype(np.int32)
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"comment {comment}"]
        + [f"element vertex {len(rec)}"]
        + props
        + [f"element face {len(tri)}", "property list uchar int vertex_indices", "end_header", ""]
    )
    return _write_atomic(path, header, [rec.tobytes(), face_rec.tobytes()])


def read_ply(path: str | os.PathLike[str]) -> PlyData:
    """Read a PLY written by this module (or any binary-LE/ASCII PLY of the same shape)."""
    path = Path(path)
    raw = path.read_bytes()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file (no 'ply' magic or no end_header)")
    body_start = raw.index(b"\n", end) + 1
    header = raw[:body_start].decode("ascii")
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, ...]]]] = []
    for line in header.splitlines():
        parts = line.split()
        if not parts:
            continue
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            elements[-1][2].append(tuple(parts[1:]))
    if fmt not in ("binary_little_endian", "ascii"):
        raise InputError(f"{path}: PLY format {fmt!r} not supported (binary_little_endian, ascii)")
    vertex: dict[str, np.ndarray] = {}
    faces = None
    if fmt == "ascii":
        lines = raw[body_start:].decode("ascii").split("\n")
        pos = 0
        for name, count, props in elements:
            rows = lines[pos : pos + count]
            pos += count
            if name == "vertex":
                table = np.array([r.split() for r in rows], dtype=float).reshape(count, -1)
                for j, p in enumerate(props):
                    vertex[p[-1]] = table[:, j].astype(_PLY_TYPES[p[0]])
            elif name == "face":
                faces = np.array([r.split()[1:4] for r in rows], dtype=np.int64).reshape(-1, 3)
        return PlyData(vertex, faces, header)
    offset = body_start
    for name, count, props in elements:
        if props and props[0][0] == "list":
            count_t, index_t = _PLY_TYPES[props[0][1]], _PLY_TYPES[props[0][2]]
            dt = np.dtype([("n", count_t), ("v", index_t, (3,))])
            rec = np.frombuffer(raw, dtype=dt, count=count, offset=offset)
            if count and not np.all(rec["n"] == 3):
                raise InputError(f"{path}: only triangle faces are supported")
            offset += rec.nbytes
            if name == "face":
                faces = rec["v"].astype(np.int64)
        else:
            dt = np.dtype([(p[1], _PLY_TYPES[p[0]]) for p in props])
            rec = np.frombuffer(raw, dtype=dt, count=count, offset=offset)
            offset += rec.nbytes
            if name == "vertex":
                vertex = {p[1]: rec[p[1]].copy() for p in props}
    return PlyData(vertex, faces, header)
