"""Small triangle meshes generated here, and a z-buffer rasteriser for them: what the appearance render draws.

Written by hand rather than with trimesh/pyrender because the render needs only an orthographic view's per-pixel
mask, depth and interpolated normal of a few thousand triangles, which ~40 lines of numpy give exactly, while an
OpenGL renderer needs a display or EGL that a headless CI machine lacks.

The teapot is *a* teapot, built from surfaces of revolution (body, lid, knob) and swept tubes (spout, handle): not
the Utah teapot's Bézier patches, which would have to be shipped.
"""

from __future__ import annotations

import numpy as np


def _grid(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a (rings, segments, 3) grid of points, closed around the segments."""
    rings, segments, _ = points.shape
    index = np.arange(rings * segments).reshape(rings, segments)
    a, b = index[:-1], np.roll(index[:-1], -1, axis=1)
    c, d = index[1:], np.roll(index[1:], -1, axis=1)
    faces = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([b, c, d], -1).reshape(-1, 3)])
    return points.reshape(-1, 3), faces


def lathe(radius: np.ndarray, height: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """The surface of revolution of the profile (radius, height) about the y axis."""
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    points = np.stack([radius[:, None] * np.cos(phi), np.broadcast_to(height[:, None], (radius.size, segments)),
                       radius[:, None] * np.sin(phi)], axis=-1)
    return _grid(points)


def tube(centre: np.ndarray, radius: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """A tube of ``radius`` (per point) swept along the polyline ``centre`` (points, 3)."""
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    helper = np.where(np.abs(tangent[:, 2:3]) < 0.9, [[0.0, 0.0, 1.0]], [[1.0, 0.0, 0.0]])
    normal = np.cross(tangent, helper)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(normal, tangent)  # the ring turns so that the faces' normals point away from the axis
    phi = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.cos(phi)[None, :, None] * normal[:, None] + np.sin(phi)[None, :, None] * binormal[:, None]
    return _grid(centre[:, None] + radius[:, None, None] * ring)


def merge(*parts) -> tuple[np.ndarray, np.ndarray]:
    vertices, faces, offset = [], [], 0
    for v, f in parts:
        vertices.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.concatenate(vertices), np.concatenate(faces)


def sphere(segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(1e-3, np.pi - 1e-3, segments // 2)
    return lathe(np.sin(theta), -np.cos(theta), segments)


def teapot(segments: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """A teapot about 2 units wide, the body's axis along y (up)."""
    t = np.linspace(0, 1, segments // 2)
    body_h = -0.6 + 1.2 * t
    body_r = 0.02 + 0.98 * np.sin(np.pi * (0.1 + 0.8 * t)) * (1 - 0.25 * t)
    lid_t = np.linspace(0, 1, 8)
    lid = lathe(0.3 * (1 - lid_t) + 0.05, 0.6 + 0.15 * np.sin(np.pi / 2 * lid_t), segments)
    knob_t = np.linspace(0, np.pi, 8)
    knob = lathe(0.12 * np.sin(knob_t) + 0.01, 0.75 + 0.12 * (1 - np.cos(knob_t)), segments)
    s = np.linspace(0, 1, 16)
    spout = tube(np.stack([0.8 + 0.55 * s, -0.2 + 0.75 * s**1.5, np.zeros_like(s)], -1), 0.16 - 0.08 * s, 16)
    a = np.linspace(-0.45 * np.pi, 0.45 * np.pi, 20)
    handle = tube(np.stack([-0.8 - 0.45 * np.cos(a), 0.05 + 0.4 * np.sin(a), np.zeros_like(a)], -1),
                  np.full(a.size, 0.07), 12)
    return merge(lathe(body_r, body_h, segments), lid, knob, spout, handle)


MESHES = {"teapot": teapot, "sphere": sphere}


def rotate(vertices: np.ndarray, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Turn about the vertical axis by ``yaw_deg``, then tilt towards the viewer by ``pitch_deg``."""
    y, p = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    yaw = np.array([[np.cos(y), 0, np.sin(y)], [0, 1, 0], [-np.sin(y), 0, np.cos(y)]])
    pitch = np.array([[1, 0, 0], [0, np.cos(p), -np.sin(p)], [0, np.sin(p), np.cos(p)]])
    return vertices @ (pitch @ yaw).T


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals, pointing out of a closed, consistently wound mesh."""
    tri = vertices[faces]
    face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, faces[:, k], face)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    return normals / np.where(length > 0, length, 1.0)


def rasterise(vertices: np.ndarray, faces: np.ndarray, shape: tuple[int, int], margin: float = 0.1
              ) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic z-buffer view along −z (the viewer at +z) of a mesh fitted into ``shape`` = (rows, cols) with
    ``margin`` of the frame free: the covered pixels and their unit normals (rows, cols, 3; 0 outside), normals
    interpolated from the vertices' (Phong shading), facing the viewer."""
    rows, cols = shape
    normals = vertex_normals(vertices, faces)
    low, high = vertices[:, :2].min(0), vertices[:, :2].max(0)
    scale = (1 - 2 * margin) * min(cols / (high[0] - low[0]), rows / (high[1] - low[1]))
    x = (vertices[:, 0] - (low[0] + high[0]) / 2) * scale + cols / 2
    y = rows / 2 - (vertices[:, 1] - (low[1] + high[1]) / 2) * scale
    depth = np.full(shape, -np.inf)
    normal = np.zeros((*shape, 3))
    for tri in faces:
        px, py, pz = x[tri], y[tri], vertices[tri, 2]
        c0, c1 = int(max(np.floor(px.min()), 0)), int(min(np.ceil(px.max()), cols - 1))
        r0, r1 = int(max(np.floor(py.min()), 0)), int(min(np.ceil(py.max()), rows - 1))
        if c0 > c1 or r0 > r1:
            continue
        gy, gx = np.mgrid[r0:r1 + 1, c0:c1 + 1] + 0.5
        area = (px[1] - px[0]) * (py[2] - py[0]) - (px[2] - px[0]) * (py[1] - py[0])
        if abs(area) < 1e-12:
            continue
        w1 = ((gx - px[0]) * (py[2] - py[0]) - (px[2] - px[0]) * (gy - py[0])) / area
        w2 = ((px[1] - px[0]) * (gy - py[0]) - (gx - px[0]) * (py[1] - py[0])) / area
        w0 = 1 - w1 - w2
        inside = (w0 >= 0) & (w1 >= 0) & (w2 >= 0)
        z = w0 * pz[0] + w1 * pz[1] + w2 * pz[2]
        window = depth[r0:r1 + 1, c0:c1 + 1]
        nearer = inside & (z > window)
        if nearer.any():
            window[nearer] = z[nearer]
            n = (w0[..., None] * normals[tri[0]] + w1[..., None] * normals[tri[1]] + w2[..., None] * normals[tri[2]])
            normal[r0:r1 + 1, c0:c1 + 1][nearer] = n[nearer]
    covered = np.isfinite(depth)
    length = np.linalg.norm(normal, axis=-1, keepdims=True)
    normal = np.where(covered[..., None], normal / np.where(length > 0, length, 1.0), 0.0)
    normal[..., 2] = np.abs(normal[..., 2]) * covered  # interpolation across a silhouette can tilt one away
    return covered, normal
