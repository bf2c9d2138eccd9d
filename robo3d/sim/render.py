"""Ray-cast rendering of the simulated cell: ambient-lit views and laser-lit frames.

The scene is the ground-truth object mesh on a dark, faintly textured table (the square
``|x|, |y| <= table_half_size`` of the plane ``z = 0``), cast with Open3D's
``RaycastingScene``. Each pixel's ray is ``camera.rays(pixel centre)`` (the exact
inverse of the plumb_bob projection), so the images are distorted exactly as the
calibration says.

Views (``render_view``)
    Lambertian: ``albedo * (ambient + direct * max(0, n . l) * lit)`` with a directional
    light ``l`` fixed in ``base`` and a shadow ray toward it; one ray per pixel centre,
    so a pixel shows the object exactly when its centre ray hits the object.
Laser frames (``render_laser_frame``)
    Dimmed ambient plus the laser: a surface point ``X`` at distance ``d`` from the sheet
    receives ``exp(-2 d^2 / w^2) * cos(theta) * r_ref / |X - o|`` (Gaussian sheet profile
    of 1/e^2 half-width ``w``, incidence angle ``theta`` between the beam and the normal,
    a fan spreading its power over its arc), but only when the laser sees it: a shadow
    ray from the laser origin ``o`` toward ``X`` must first hit ``X`` itself. The camera
    sees it by Lambertian reflection. Pixels near the stripe are supersampled
    (``supersample x supersample`` rays over the pixel's area), so the stripe's profile
    is the pixel-integrated one and its sub-pixel centre is unbiased by the sampling.
Sensor (``sensor_noise``)
    Shot noise (Poisson electrons, ``gain`` DN per electron), Gaussian read noise,
    rounding and clipping to 8 bits.

Normals used for shading are interpolated vertex normals (smooth shading of the truth
mesh); hit points are on the mesh's exact triangles.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ..camera import CameraModel
from .shapes import TriangleMesh

__all__ = [
    "Appearance",
    "SimScene",
    "Hits",
    "render_view",
    "render_laser_frame",
    "sensor_noise",
    "pixel_grid_rays",
]

MISS, OBJECT, TABLE = 0, 1, 2


@dataclass(frozen=True)
class Appearance:
    """Materials, lights and laser of the simulated cell (all radiometric quantities in
    8-bit digital numbers, DN).

    Attributes
    ----------
    object_albedo : (3,) float
        RGB albedo of the matte object (its mean is the laser's albedo).
    table_albedo : float
        Mean albedo of the dark table.
    table_texture : float
        Relative amplitude of the table's faint procedural grain (0 for none).
    background : float
        Radiance of rays that miss everything, as a fraction of ``view_exposure_dn``.
    light_dir : (3,) float
        Direction toward the directional light in ``base``.
    ambient, direct : float
        Ambient and directional light strengths of the views.
    view_exposure_dn : float
        DN of a white (albedo 1) surface under ``ambient + direct`` light.
    laser_ambient_dn : float
        DN of the object under the dimmed ambient of the laser frames (the table gets
        ``table_albedo / mean(object_albedo)`` of it). An integer keeps the flat dark
        regions of the frames nearly constant after quantisation, so they compress well.
    laser_peak_dn : float
        DN of the stripe's peak on the object at normal incidence, at range
        ``laser_reference_range`` from the laser.
    laser_width : float, metres
        1/e^2 half-width ``w`` of the laser sheet at the surface.
    laser_fan_deg : float, degrees
        Half-angle of the laser's fan.
    laser_reference_range : float, metres
    supersample : int
        Rays per pixel side near the stripe.
    """

    object_albedo: tuple[float, float, float] = (0.74, 0.70, 0.64)
    table_albedo: float = 0.07
    table_texture: float = 0.25
    background: float = 0.02
    light_dir: tuple[float, float, float] = (0.35, -0.45, 0.82)
    ambient: float = 0.35
    direct: float = 0.65
    view_exposure_dn: float = 250.0
    laser_ambient_dn: float = 1.0
    laser_peak_dn: float = 200.0
    laser_width: float = 0.0003
    laser_fan_deg: float = 30.0
    laser_reference_range: float = 0.28
    supersample: int = 3


@dataclass
class Hits:
    """First hits of a batch of rays.

    Attributes
    ----------
    kind : (N,) int8
        0 miss, 1 object, 2 table.
    t : (N,) float64, metres
        Distance along the (unit) ray; ``inf`` on a miss.
    points : (N, 3) float64, metres
        Hit points in ``base`` (zeros on a miss).
    normals : (N, 3) float64
        Unit shading normals (zeros on a miss).
    """

    kind: np.ndarray
    t: np.ndarray
    points: np.ndarray
    normals: np.ndarray


def _table_pattern(xy: np.ndarray) -> np.ndarray:
    """A faint wood-grain pattern in [-1, 1] over base x, y (metres)."""
    x, y = xy[:, 0], xy[:, 1]
    warp = 0.004 * np.sin(2 * np.pi * 7.0 * y + 1.3) + 0.002 * np.sin(2 * np.pi * 19.0 * x)
    return (0.6 * np.sin(2 * np.pi * 61.0 * (x + warp))
            + 0.4 * np.sin(2 * np.pi * 23.0 * (0.8 * x + 0.6 * y) + 0.7))


class SimScene:
    """The object mesh on the table, ready for ray casting.

    Parameters
    ----------
    mesh : TriangleMesh
        The ground-truth object in ``base`` (metres).
    appearance : Appearance
    table_half_size : float, metres
        The table is the square ``|x|, |y| <= table_half_size`` at ``z = 0``.
    threads : int
        Ray-casting threads (0: all cores). Results do not depend on it.
    """

    def __init__(self, mesh: TriangleMesh, appearance: Appearance | None = None,
                 table_half_size: float = 0.6, threads: int = 1) -> None:
        import open3d as o3d

        self.mesh = mesh
        self.appearance = appearance or Appearance()
        self.threads = int(threads)
        self._o3d = o3d
        self._scene = o3d.t.geometry.RaycastingScene()
        v = np.ascontiguousarray(mesh.vertices, dtype=np.float32)
        f = np.ascontiguousarray(mesh.faces, dtype=np.uint32)
        self._object_id = self._scene.add_triangles(o3d.core.Tensor(v), o3d.core.Tensor(f))
        s = float(table_half_size)
        tv = np.array([[-s, -s, 0], [s, -s, 0], [s, s, 0], [-s, s, 0]], dtype=np.float32)
        tf = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.uint32)
        self._table_id = self._scene.add_triangles(o3d.core.Tensor(tv), o3d.core.Tensor(tf))
        self._vertex_normals = mesh.vertex_normals()
        self._faces = mesh.faces
        self._ray_cache: dict[tuple, np.ndarray] = {}

    # ------------------------------------------------------------------ casting
    def _cast_raw(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        out = self._scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.threads)
        return {k: v.numpy() for k, v in out.items()}

    def cast(self, origins: np.ndarray, dirs: np.ndarray, normals: bool = True) -> Hits:
        """First hits of rays.

        Parameters
        ----------
        origins : (3,) or (N, 3) float64, metres
        dirs : (N, 3) float64
            Unit directions in ``base``.
        normals : bool
            Compute the shading normals (else they are left zero).

        Returns
        -------
        Hits
        """
        dirs = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), dirs.shape)
        raw = self._cast_raw(origins, dirs)
        t = raw["t_hit"].astype(np.float64)
        gid = raw["geometry_ids"]
        kind = np.zeros(len(t), dtype=np.int8)
        kind[gid == self._object_id] = OBJECT
        kind[gid == self._table_id] = TABLE
        hit = kind != MISS
        points = origins + np.where(hit, t, 0.0)[:, None] * dirs
        points[~hit] = 0.0
        normals_ = np.zeros_like(dirs)
        obj = kind == OBJECT
        if normals and np.any(obj):
            prim = raw["primitive_ids"][obj].astype(np.int64)
            uv = raw["primitive_uvs"][obj].astype(np.float64)
            tri = self._faces[prim]
            vn = self._vertex_normals
            n = ((1 - uv[:, 0] - uv[:, 1])[:, None] * vn[tri[:, 0]]
                 + uv[:, 0:1] * vn[tri[:, 1]] + uv[:, 1:2] * vn[tri[:, 2]])
            normals_[obj] = n / np.linalg.norm(n, axis=1, keepdims=True)
        if normals:
            normals_[kind == TABLE] = (0.0, 0.0, 1.0)
        return Hits(kind, t, points, normals_)

    def first_hit_distance(self, origins: np.ndarray, vectors: np.ndarray) -> np.ndarray:
        """Fraction ``t`` along ``origins + t * vectors`` of the first hit (``inf``: none).

        Parameters
        ----------
        origins : (3,) or (N, 3) float64, metres
        vectors : (N, 3) float64, metres (not normalised: ``t = 1`` is the vector's tip)
        """
        vectors = np.asarray(vectors, dtype=np.float64).reshape(-1, 3)
        origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), vectors.shape)
        return self._cast_raw(origins, vectors)["t_hit"].astype(np.float64)

    # ------------------------------------------------------------------ materials
    def albedo_grey(self, hits: Hits, texture: bool = True) -> np.ndarray:
        """Grey albedo ``(N,)`` at the hits (0 on a miss); ``texture=False`` gives the
        table its mean albedo."""
        a = self.appearance
        lut = np.array([0.0, float(np.mean(a.object_albedo)), a.table_albedo])
        out = lut[hits.kind]
        if texture and a.table_texture:
            table = hits.kind == TABLE
            out[table] *= 1 + a.table_texture * _table_pattern(hits.points[table])
        return out

    def albedo_rgb(self, hits: Hits) -> np.ndarray:
        """RGB albedo ``(N, 3)`` at the hits (0 on a miss)."""
        a = self.appearance
        out = np.zeros((len(hits.kind), 3))
        out[hits.kind == OBJECT] = a.object_albedo
        table = hits.kind == TABLE
        grain = a.table_albedo * (1 + a.table_texture * _table_pattern(hits.points[table]))
        out[table] = grain[:, None] * np.array([1.08, 1.0, 0.9])
        return out

    def pixel_rays(self, camera: CameraModel) -> np.ndarray:
        """Unit ray directions ``(H * W, 3)`` of every pixel centre in the camera frame
        (row-major), cached per camera."""
        key = (camera.width, camera.height, camera.K.tobytes(), camera.D.tobytes())
        if key not in self._ray_cache:
            self._ray_cache[key] = pixel_grid_rays(camera)
        return self._ray_cache[key]


def pixel_grid_rays(camera: CameraModel) -> np.ndarray:
    """Unit ray directions ``(H * W, 3)`` in the camera frame through every pixel centre,
    row-major (index ``v * W + u``)."""
    u, v = np.meshgrid(np.arange(camera.width, dtype=np.float64),
                       np.arange(camera.height, dtype=np.float64))
    return camera.rays(np.stack([u.ravel(), v.ravel()], axis=1))


def render_view(scene: SimScene, camera: CameraModel, T_base_camera: np.ndarray) -> np.ndarray:
    """Noise-free ambient-lit view of the scene.

    Parameters
    ----------
    scene : SimScene
    camera : CameraModel
    T_base_camera : (4, 4) float64

    Returns
    -------
    (H, W, 3) float64, DN
        RGB signal before sensor noise.
    """
    a = scene.appearance
    t = np.asarray(T_base_camera, dtype=np.float64)
    dirs = scene.pixel_rays(camera) @ t[:3, :3].T
    hits = scene.cast(t[:3, 3], dirs)
    light = np.asarray(a.light_dir, dtype=np.float64)
    light = light / np.linalg.norm(light)
    hit = hits.kind != MISS
    shade = np.maximum(hits.normals @ light, 0.0)  # zero on a miss (zero normal)
    lit_idx = np.flatnonzero(shade > 0)
    if len(lit_idx):  # shadow rays toward the light, started just off the surface
        start = hits.points[lit_idx] + 2e-5 * hits.normals[lit_idx]
        blocked = np.isfinite(scene.first_hit_distance(
            start, np.broadcast_to(light, (len(lit_idx), 3))))
        shade[lit_idx[blocked]] = 0.0
    irradiance = a.ambient + a.direct * shade
    rgb = scene.albedo_rgb(hits) * irradiance[:, None]
    rgb[~hit] = a.background
    return (rgb * a.view_exposure_dn).reshape(camera.height, camera.width, 3)


def _laser_dn(scene: SimScene, hits: Hits, T_base_laser: np.ndarray) -> np.ndarray:
    """Laser-lit DN ``(N,)`` of hit points (0 where unlit, off the sheet or shadowed)."""
    a = scene.appearance
    out = np.zeros(len(hits.kind))
    hit = hits.kind != MISS
    o = T_base_laser[:3, 3]
    r_l = T_base_laser[:3, :3]
    p_l = (hits.points - o) @ r_l  # laser coordinates
    w = a.laser_width
    gauss = np.exp(-2.0 * (p_l[:, 1] / w) ** 2)
    in_fan = (p_l[:, 2] > 0) & (np.abs(np.arctan2(p_l[:, 0], p_l[:, 2]))
                                <= np.radians(a.laser_fan_deg))
    cand = np.nonzero(hit & in_fan & (gauss > 1e-6))[0]
    if len(cand) == 0:
        return out
    vec = hits.points[cand] - o
    rng_ = np.linalg.norm(vec, axis=1)
    cos = np.maximum(-np.einsum("ij,ij->i", hits.normals[cand], vec) / rng_, 0.0)
    t_first = scene.first_hit_distance(o, vec)
    lit = t_first >= 1.0 - 5e-5 / rng_
    albedo = scene.albedo_grey(hits)[cand]
    scale = a.laser_peak_dn / float(np.mean(a.object_albedo))
    out[cand] = (scale * albedo * gauss[cand] * cos * (a.laser_reference_range / rng_)
                 * lit)
    return out


def render_laser_frame(scene: SimScene, camera: CameraModel, T_base_camera: np.ndarray,
                       T_base_laser: np.ndarray) -> np.ndarray:
    """Noise-free laser-lit frame (dimmed ambient plus the stripe).

    Parameters
    ----------
    scene : SimScene
    camera : CameraModel
    T_base_camera : (4, 4) float64
    T_base_laser : (4, 4) float64
        The laser frame in ``base``; the sheet is its x-z plane.

    Returns
    -------
    (H, W) float64, DN
        Grey signal before sensor noise.
    """
    a = scene.appearance
    t = np.asarray(T_base_camera, dtype=np.float64)
    t_l = np.asarray(T_base_laser, dtype=np.float64)
    h, w = camera.height, camera.width
    ambient = a.laser_ambient_dn / float(np.mean(a.object_albedo))
    dirs = scene.pixel_rays(camera) @ t[:3, :3].T
    hits = scene.cast(t[:3, 3], dirs, normals=False)
    # the dimmed ambient is far below one DN on the table: its grain is not rendered
    image = scene.albedo_grey(hits, texture=False) * ambient
    # pixels whose centre lands near the sheet, dilated by one pixel, are supersampled
    d = np.abs((hits.points - t_l[:3, 3]) @ t_l[:3, 1])
    footprint = np.where(np.isfinite(hits.t), hits.t, 0.0) / camera.fx
    near = (hits.kind != MISS) & (d < 2.0 * a.laser_width + 1.0 * footprint)
    near = cv2.dilate(near.reshape(h, w).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    idx = np.flatnonzero(near)
    if len(idx) == 0:
        return image.reshape(h, w)
    s = max(int(a.supersample), 1)
    offs = (np.arange(s) + 0.5) / s - 0.5
    du, dv = np.meshgrid(offs, offs)
    uv = np.stack([idx % w, idx // w], axis=1).astype(np.float64)
    sub_uv = (uv[:, None, :] + np.stack([du.ravel(), dv.ravel()], axis=1)[None]).reshape(-1, 2)
    sub_dirs = camera.rays(sub_uv) @ t[:3, :3].T
    sub = scene.cast(t[:3, 3], sub_dirs)
    sub_dn = scene.albedo_grey(sub, texture=False) * ambient + _laser_dn(scene, sub, t_l)
    image[idx] = sub_dn.reshape(len(idx), s * s).mean(axis=1)
    return image.reshape(h, w)


def sensor_noise(signal_dn: np.ndarray, rng: np.random.Generator, gain: float,
                 read_noise: float) -> np.ndarray:
    """Add shot and read noise to a signal and quantise it to 8 bits.

    Parameters
    ----------
    signal_dn : (H, W) or (H, W, 3) float64, DN
    rng : numpy Generator
    gain : float, DN per electron
        Shot noise: the signal is ``gain * Poisson(signal / gain)`` (0: none).
    read_noise : float, DN
        Standard deviation of Gaussian read noise.

    Returns
    -------
    uint8 array of the same shape
    """
    s = np.maximum(np.asarray(signal_dn, dtype=np.float64), 0.0)
    if gain > 0:
        s = rng.poisson(s / gain) * gain
    if read_noise > 0:
        s = s + rng.normal(0.0, read_noise, s.shape)
    return np.clip(np.rint(s), 0, 255).astype(np.uint8)
