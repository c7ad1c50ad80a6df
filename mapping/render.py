"""A small z-buffer point-splat renderer for looking at meshes (previews, benchmarks, tests).

Not a rasteriser of record: each triangle is splatted as its three vertices and a few
barycentric samples into a z-buffer, shaded by a headlight on the vertex normals (or coloured
by vertex colours), then small holes are closed. Enough to see whether a fused mesh is sane.
"""

from __future__ import annotations

import cv2
import numpy as np

from mapping.mesh import TriangleMesh


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """world_from_cam (4x4) of a camera at ``eye`` looking at ``target`` (x right, y down)."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, float))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    out = np.eye(4)
    out[:3, :3] = np.stack([x, y, z], axis=1)
    out[:3, 3] = eye
    return out


def render_mesh(
    mesh: TriangleMesh,
    world_from_cam: np.ndarray,
    K: np.ndarray,
    size_wh: tuple[int, int] = (960, 720),
    use_colors: bool = True,
    samples_per_face: int = 6,
    cull_back_faces: bool = False,
) -> np.ndarray:
    """Render to an (H, W, 3) uint8 RGB image (white background). ``cull_back_faces``: leave
    out faces whose vertex normals point away from the camera (e.g. the outside of a room's
    near walls, seen from outside)."""
    w, h = size_wh
    img = np.full((h, w, 3), 255, np.uint8)
    f = mesh.faces.astype(np.int64)
    v = mesh.vertices_m.astype(np.float64)
    if cull_back_faces and len(f):
        centre = v[f].mean(axis=1)
        normal = mesh.normals[f].astype(np.float64).sum(axis=1)
        f = f[np.sum(normal * (world_from_cam[:3, 3] - centre), axis=1) > 0]
    if len(f) == 0:
        return img
    rng = np.random.default_rng(0)
    bary = rng.dirichlet(np.ones(3), size=samples_per_face)
    bary = np.concatenate([np.eye(3), bary, np.full((1, 3), 1 / 3)])  # (S, 3)
    pts = np.einsum("sk,mkd->msd", bary, v[f]).reshape(-1, 3)
    nrm = np.einsum("sk,mkd->msd", bary, mesh.normals[f].astype(np.float64)).reshape(-1, 3)
    cam_from_world = np.linalg.inv(world_from_cam)
    pc = pts @ cam_from_world[:3, :3].T + cam_from_world[:3, 3]
    nc = nrm @ cam_from_world[:3, :3].T
    front = pc[:, 2] > 1e-3
    pc, nc = pc[front], nc[front]
    u = np.round(K[0, 0] * pc[:, 0] / pc[:, 2] + K[0, 2]).astype(np.int64)
    vv = np.round(K[1, 1] * pc[:, 1] / pc[:, 2] + K[1, 2]).astype(np.int64)
    ok = (u >= 0) & (u < w) & (vv >= 0) & (vv < h)
    u, vv, z, nc = u[ok], vv[ok], pc[ok, 2], nc[ok]
    view = pc[ok] / np.linalg.norm(pc[ok], axis=1, keepdims=True)
    shade = np.clip(np.abs(np.sum(nc * view, axis=1)), 0.0, 1.0) * 0.8 + 0.2
    if use_colors and mesh.colors_rgb is not None and mesh.colors_rgb.any():
        col = np.einsum("sk,mkd->msd", bary, mesh.colors_rgb[f].astype(np.float64)).reshape(-1, 3)[
            front
        ][ok]
        col = col * (0.5 + 0.5 * shade[:, None])
    else:
        col = np.repeat(shade[:, None] * 230.0, 3, axis=1)
    pix = vv * w + u
    order = np.lexsort((z, pix))  # nearest first within each pixel
    pix_s = pix[order]
    first = np.ones(len(pix_s), bool)
    first[1:] = pix_s[1:] != pix_s[:-1]
    sel = order[first]
    flat = img.reshape(-1, 3)
    flat[pix[sel]] = np.clip(col[sel], 0, 255).astype(np.uint8)
    hit_flat = np.zeros(h * w, np.uint8)
    hit_flat[pix[sel]] = 1
    hit = hit_flat.reshape(h, w)
    closed = cv2.morphologyEx(img, cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8))
    holes = (hit == 0) & (cv2.dilate(hit, np.ones((3, 3), np.uint8)) > 0)
    img[holes] = closed[holes]
    return img
