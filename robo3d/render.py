"""Headless pictures of meshes: Open3D ray casting (Embree, no display, no OpenGL).

:func:`render_mesh` casts one ray per pixel of a pinhole camera looking at the mesh from a
given azimuth and elevation, shades each hit with a headlight and a key light (Lambert)
and colours it by a per-vertex scalar (e.g. the distance to the true surface) through a
colour map, interpolated over the triangle with the hit's barycentric coordinates.
:func:`error_figure` puts several views side by side with a colour bar and writes a PNG.

Choices
-------
- Ray casting rather than an OpenGL renderer: it runs on any server, in CI and inside
  Snakemake jobs without a display, and is deterministic.
- Colour map: a perceptually ordered blue-green-yellow-red ramp built in (no matplotlib
  dependency); values above ``vmax`` saturate, NaN (no value) is grey.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["colormap", "view_basis", "render_mesh", "render_mesh_views", "render_points",
           "error_figure"]

log = logging.getLogger(__name__)

_RAMP = np.array([[0.19, 0.25, 0.65], [0.13, 0.55, 0.80], [0.20, 0.72, 0.50],
                  [0.65, 0.80, 0.20], [0.98, 0.80, 0.15], [0.95, 0.45, 0.10],
                  [0.80, 0.10, 0.10]])


def colormap(values: np.ndarray, vmax: float, vmin: float = 0.0) -> np.ndarray:
    """Colours (N, 3) float in [0, 1] of values on a blue-to-red ramp; NaN is grey.

    Parameters
    ----------
    values : (N,) float
    vmax, vmin : float
        Values at the ends of the ramp (outside: clamped).
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if not vmax > vmin:
        raise ValueError(f"vmax must be > vmin, got {vmax} and {vmin}")
    t = np.clip((np.nan_to_num(v, nan=vmin) - vmin) / (vmax - vmin), 0.0, 1.0)
    x = t * (len(_RAMP) - 1)
    i = np.minimum(np.floor(x).astype(int), len(_RAMP) - 2)
    a = (x - i)[:, None]
    out = _RAMP[i] * (1 - a) + _RAMP[i + 1] * a
    out[np.isnan(v)] = 0.6
    return out


def view_basis(up: np.ndarray | None = None) -> np.ndarray:
    """A right-handed basis ``(e1, e2, up)`` (rows) for azimuth and elevation about ``up``.

    Azimuth 0 looks from ``e1``: the frame axis least aligned with ``up`` (x for z up),
    made perpendicular to it, so that z up gives ``(x, y, z)`` and the pictures of a z-up
    object are those rendered before ``up`` existed; ``e2 = up x e1``.
    """
    u = np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, dtype=np.float64)
    if u.shape != (3,) or not np.linalg.norm(u) > 0:
        raise ValueError(f"up must be a non-zero (3,) vector, got {u!r}")
    u = u / np.linalg.norm(u)
    a = np.eye(3)[int(np.argmin(np.abs(u)))]
    e1 = a - (a @ u) * u
    e1 /= np.linalg.norm(e1)
    return np.stack([e1, np.cross(u, e1), u])


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    z = target - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:  # looking straight along up: any side will do
        x = np.cross(z, view_basis(up)[1])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], axis=1)  # columns: camera axes in world


def _key(up: np.ndarray | None) -> np.ndarray:
    """The key light's direction: from above and to one side, about ``up``."""
    k = np.array([0.3, -0.4, 0.87]) @ view_basis(up)
    return k / np.linalg.norm(k)


def _camera(points: np.ndarray, azimuth_deg: float, elevation_deg: float,
            up: np.ndarray | None, width: int, height: int, fov_deg: float):
    """Eye, rotation (columns: camera axes in world), focal length in pixels and centre of
    a pinhole camera that frames the points' bounding sphere from the given direction."""
    if width < 8 or height < 8:
        raise ValueError(f"image must be at least 8 x 8 pixels, got {width} x {height}")
    centre = 0.5 * (points.min(axis=0) + points.max(axis=0))
    radius = max(float(np.linalg.norm(points - centre, axis=1).max()), 1e-9)
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    direction = (np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
                 @ view_basis(up))
    half = min(np.radians(fov_deg) / 2,  # frame the bounding sphere in both directions
               np.arctan(np.tan(np.radians(fov_deg) / 2) * height / width))
    eye = centre + radius / np.sin(half) * 1.05 * direction
    fpx = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    return eye, _look_at(eye, centre, view_basis(up)[2]), fpx, centre


def render_mesh(vertices: np.ndarray, faces: np.ndarray, *, vertex_colors: np.ndarray | None = None,
                azimuth_deg: float = 30.0, elevation_deg: float = 35.0, width: int = 480,
                height: int = 360, fov_deg: float = 30.0, background: float = 1.0,
                threads: int = 1, up: np.ndarray | None = None) -> np.ndarray:
    """Render a triangle mesh headless by ray casting.

    Parameters
    ----------
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    vertex_colors : (V, 3) float in [0, 1], optional
        Default: light grey.
    azimuth_deg, elevation_deg : float, degrees
        Direction from the mesh's centre to the camera, about ``up`` (:func:`view_basis`).
    width, height : int
        Image size, pixels.
    fov_deg : float
        Horizontal field of view; the camera distance frames the mesh's bounding sphere.
    background : float in [0, 1]
        Grey level of pixels that miss the mesh.
    threads : int
        Ray-casting threads (0: all cores).
    up : (3,) float, optional
        The object's up direction, drawn upwards in the image (default +z).

    Returns
    -------
    (height, width, 3) uint8
        RGB image.
    """
    return render_mesh_views(vertices, faces, ((azimuth_deg, elevation_deg),),
                             vertex_colors=vertex_colors, width=width, height=height,
                             fov_deg=fov_deg, background=background, threads=threads, up=up)[0]


def render_mesh_views(vertices: np.ndarray, faces: np.ndarray,
                      views: Sequence[tuple[float, float]], *,
                      vertex_colors: np.ndarray | None = None, width: int = 480,
                      height: int = 360, fov_deg: float = 30.0, background: float = 1.0,
                      threads: int = 1, up: np.ndarray | None = None) -> list[np.ndarray]:
    """:func:`render_mesh` from several ``(azimuth_deg, elevation_deg)`` directions,
    building the ray-casting scene (its BVH, most of the cost) once for all of them.

    Returns
    -------
    list of (height, width, 3) uint8
        One RGB image per view, each the same as :func:`render_mesh` gives.
    """
    import open3d as o3d

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"vertices must be (V, 3), got {v.shape}")
    if width < 8 or height < 8:
        raise ValueError(f"image must be at least 8 x 8 pixels, got {width} x {height}")
    col = (np.full((len(v), 3), 0.8) if vertex_colors is None
           else np.asarray(vertex_colors, dtype=np.float64))
    if col.shape != (len(v), 3):
        raise ValueError(f"vertex_colors must be ({len(v)}, 3), got {col.shape}")
    blank = (np.full((height, width, 3), background) * 255).round().astype(np.uint8)
    if len(f) == 0:
        return [blank.copy() for _ in views]
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    scene = o3d.t.geometry.RaycastingScene(nthreads=int(threads))
    scene.add_triangles(o3d.core.Tensor((v - centre).astype(np.float32)),
                        o3d.core.Tensor(f.astype(np.uint32)))
    uu, vv = np.meshgrid(np.arange(width) - (width - 1) / 2, np.arange(height) - (height - 1) / 2)
    out = []
    for azimuth_deg, elevation_deg in views:
        eye, rot, fpx, _ = _camera(v, azimuth_deg, elevation_deg, up, width, height, fov_deg)
        d = np.stack([uu / fpx, vv / fpx, np.ones_like(uu)], axis=-1).reshape(-1, 3) @ rot.T
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        rays = np.hstack([np.broadcast_to(eye - centre, d.shape), d]).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        ok = np.isfinite(hit["t_hit"].numpy())
        prim = hit["primitive_ids"].numpy()[ok].astype(np.int64)
        uv = hit["primitive_uvs"].numpy()[ok].astype(np.float64)
        n = hit["primitive_normals"].numpy()[ok].astype(np.float64)
        tri = f[prim]
        c = (col[tri[:, 0]] * (1 - uv[:, 0] - uv[:, 1])[:, None] + col[tri[:, 1]] * uv[:, 0:1]
             + col[tri[:, 2]] * uv[:, 1:2])
        dd = d[ok]
        n = np.where((np.einsum("ij,ij->i", n, dd) > 0)[:, None], -n, n)  # face the camera
        shade = (0.25 + 0.5 * np.abs(np.einsum("ij,ij->i", n, -dd))
                 + 0.25 * np.clip(n @ _key(up), 0, 1))
        img = np.full((height * width, 3), background, dtype=np.float64)
        img[ok] = np.clip(c * shade[:, None], 0, 1)
        out.append((img.reshape(height, width, 3) * 255).round().astype(np.uint8))
    return out


def error_figure(path: str | Path, vertices: np.ndarray, faces: np.ndarray,
                 errors_mm: np.ndarray, *, vmax_mm: float = 0.2, title: str = "",
                 views: tuple[tuple[float, float], ...] = ((30, 35), (150, 35), (270, 60),
                                                           (0, 89)),
                 width: int = 420, height: int = 320) -> Path:
    """Write a PNG of a mesh coloured by a per-vertex error, from several directions.

    Parameters
    ----------
    path : str or Path
        The PNG to write (atomically).
    vertices : (V, 3) float64, metres
    faces : (F, 3) int
    errors_mm : (V,) float, millimetres
        E.g. each vertex's distance to the true surface (NaN: grey).
    vmax_mm : float
        Error at the red end of the colour bar.
    title : str
        Written above the pictures.
    views : tuple of (azimuth, elevation) in degrees
    width, height : int
        Size of each view.

    Returns
    -------
    Path
    """
    import cv2

    from .atomic import atomic_path

    err = np.asarray(errors_mm, dtype=np.float64).ravel()
    if err.shape != (len(vertices),):
        raise ValueError(f"errors_mm must be ({len(vertices)},), got {err.shape}")
    col = colormap(err, vmax_mm)
    tiles = render_mesh_views(vertices, faces, views, vertex_colors=col, width=width,
                              height=height)
    row = np.concatenate(tiles, axis=1)
    bar_h, pad = 40, 10
    bar = np.full((bar_h + 30, row.shape[1], 3), 255, dtype=np.uint8)
    ramp = colormap(np.linspace(0, vmax_mm, row.shape[1] // 2), vmax_mm)
    x0 = row.shape[1] // 4
    bar[pad:pad + 16, x0:x0 + len(ramp)] = (ramp[None] * 255).astype(np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    black = (0, 0, 0)
    cv2.putText(bar, "0 mm", (x0 - 60, pad + 14), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(bar, f">= {vmax_mm:g} mm from the true surface", (x0 + len(ramp) + 8, pad + 14),
                font, 0.5, black, 1, cv2.LINE_AA)
    head = np.full((30, row.shape[1], 3), 255, dtype=np.uint8)
    cv2.putText(head, title, (10, 21), font, 0.6, black, 1, cv2.LINE_AA)
    out = np.concatenate([head, row, bar], axis=0)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(out, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path


def render_points(points: np.ndarray, colors: np.ndarray, *, normals: np.ndarray | None = None,
                  azimuth_deg: float = 30.0, elevation_deg: float = 35.0, width: int = 480,
                  height: int = 360, fov_deg: float = 30.0, background: float = 1.0,
                  up: np.ndarray | None = None, splat_px: int = 2) -> np.ndarray:
    """Render a point cloud headless: each point a ``splat_px`` square, the nearest point
    winning each pixel (a z-buffer by sorting, no loop over points).

    Parameters
    ----------
    points : (N, 3) float64, metres
    colors : (N, 3) float in [0, 1]
    normals : (N, 3) float, optional
        Shade each point by the angle between its normal and the line of sight (points
        seen edge-on darker), which gives the cloud its shape; flat colour without.
    azimuth_deg, elevation_deg, width, height, fov_deg, background, up
        As :func:`render_mesh` (the camera frames the cloud's bounding sphere).
    splat_px : int
        Side of each point's square, pixels.

    Returns
    -------
    (height, width, 3) uint8
        RGB image.
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    col = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
    if col.shape != p.shape:
        raise ValueError(f"colors must be ({len(p)}, 3), got {col.shape}")
    img = np.full((height * width, 3), background, dtype=np.float64)
    if not len(p):
        return (img.reshape(height, width, 3) * 255).round().astype(np.uint8)
    eye, rot, fpx, _ = _camera(p, azimuth_deg, elevation_deg, up, width, height, fov_deg)
    q = (p - eye) @ rot  # camera coordinates
    z = q[:, 2]
    if normals is not None:
        n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
        sight = (p - eye) / np.linalg.norm(p - eye, axis=1, keepdims=True)
        col = col * (0.35 + 0.65 * np.abs(np.einsum("ij,ij->i", n, sight)))[:, None]
    u = np.floor(fpx * q[:, 0] / z + (width - 1) / 2).astype(np.int64)
    v = np.floor(fpx * q[:, 1] / z + (height - 1) / 2).astype(np.int64)
    off = np.arange(splat_px) - (splat_px - 1) // 2
    ou, ov = np.meshgrid(off, off)
    uu = (u[:, None] + ou.ravel()).ravel()
    vv = (v[:, None] + ov.ravel()).ravel()
    idx = np.repeat(np.arange(len(p)), ou.size)
    ok = (uu >= 0) & (uu < width) & (vv >= 0) & (vv < height) & (z[idx] > 0)
    pix = vv[ok] * width + uu[ok]
    idx = idx[ok]
    order = np.lexsort((z[idx], pix))  # by pixel, nearest first
    first = np.unique(pix[order], return_index=True)[1]
    win = order[first]
    img[pix[win]] = np.clip(col[idx[win]], 0, 1)
    return (img.reshape(height, width, 3) * 255).round().astype(np.uint8)
