"""Ray-cast rendering of the simulated cell: ambient-lit views and laser-lit frames.

The scene is the ground-truth object mesh on a dark, faintly textured table (the square
``|x|, |y| <= table_half_size`` of the plane ``z = 0``), cast with Open3D's
``RaycastingScene``. Each pixel's ray is ``camera.rays(pixel centre)`` (the exact
inverse of the plumb_bob projection), so the images are distorted exactly as the
calibration says.

Views (``render_view``)
    Lambertian: ``albedo * (ambient + direct * max(0, n . l) * lit)`` with a directional
    light ``l`` fixed in ``base`` and a shadow ray toward it; one ray per pixel centre,
    except on geometric edges (the object's outline, occluding edges, the table's and
    the wall's borders), where a pixel is the mean of ``view_supersample`` squared rays
    over its area, as a sensor integrates the light falling on it. The true silhouette
    is the pixels whose centre ray hits the object.
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

A real-looking cell (issue 10, :meth:`Appearance.cell`; every option off by default)
    - the scene gains a vertical wall (a quad, ``wall_distance`` from the origin) and
      the table a printed pattern (ArUco-like squares with random bits from an integer
      hash, a checkerboard or dots, on ``|x|, |y| <= 0.2 m``, clear of the object);
    - the object gets a procedural solid texture (a function of the 3-D hit point, so
      it needs no UV map and is the same in every view) and a Blinn-Phong highlight
      (Blinn 1977) of the directional light;
    - laser frames are room-lit: the view's rendering at the frame's pose times
      ``laser_ambient_fraction``, at pixel centres, plus the laser supersampled as
      above; a coloured laser is one wavelength, so its reflection is the albedo in
      the laser's main channel times the sensor's response ``laser_rgb`` (the other
      channels see a little of it, as the Bayer filters overlap), and it glints where
      the object mirrors it toward the camera (``laser_specular``);
    - :func:`visible_stripe_points` gives each frame's true stripe (the points the sheet
      lights and the camera sees, with their pixels) for scoring detectors.

Reference: Blinn, J. F. (1977). Models of light reflection for computer synthesized
pictures. SIGGRAPH '77.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

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
    "vignetting",
    "speckle_gain",
    "visible_stripe_points",
    "StripeTruth",
    "LASER_RGB",
    "OBJECT_COLORS",
    "OBJECT_TEXTURES",
    "TABLE_MARKERS",
    "object_texture_weight",
    "table_marker_ink",
]

MISS, OBJECT, TABLE, WALL = 0, 1, 2, 3

#: The laser's colour as a webcam's Bayer RGB sensor records it (relative response of
#: R, G, B to the laser's single wavelength: 650 nm red, 520 nm green, 450 nm blue;
#: the colour filters overlap, so the other channels see a little of it).
LASER_RGB: dict[str, tuple[float, float, float]] = {
    "red": (1.0, 0.12, 0.06),
    "green": (0.22, 1.0, 0.32),
    "blue": (0.10, 0.38, 1.0),
}
#: Named RGB albedos for ``object_color`` (``Appearance.cell``, ``--object-color``).
OBJECT_COLORS: dict[str, tuple[float, float, float]] = {
    "grey": (0.74, 0.70, 0.64), "white": (0.88, 0.87, 0.84), "orange": (0.86, 0.40, 0.10),
    "red": (0.72, 0.12, 0.10), "green": (0.22, 0.56, 0.26), "blue": (0.14, 0.30, 0.72),
    "yellow": (0.85, 0.75, 0.15), "brown": (0.48, 0.28, 0.15), "black": (0.07, 0.07, 0.07),
}
#: Procedural solid textures of the object (``Appearance.object_texture``).
OBJECT_TEXTURES: tuple[str, ...] = ("none", "blotches", "checker", "stripes")
#: Printed patterns on the table (``Appearance.table_markers``).
TABLE_MARKERS: tuple[str, ...] = ("none", "aruco", "checker", "dots")


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
    view_supersample : int
        Rays per pixel side on the views' geometric edges (1: pixel centres only, the
        staircase outline of the renderer before 2026-12-03).

    The fields below make the cell look like a real one (issue 10); at their defaults
    the images are exactly those of the demo cell. :meth:`cell` sets them all.

    laser_rgb : (3,) float or None
        The laser's colour on the RGB sensor (:data:`LASER_RGB`): laser frames become
        RGB, the stripe is ``laser_rgb`` times the albedo at the laser's wavelength (the
        object's albedo in the laser's strongest channel). ``None``: grey frames.
    laser_ambient_fraction : float or None
        Room light in the laser frames: they are the view's rendering (ambient, direct
        light, shadows, texture, glints) times this fraction (0.4-0.7 in a lit room),
        plus the laser. ``None``: the dimmed ``laser_ambient_dn``.
        With either of the two set, the stripe's peak is ``laser_peak_dn`` per unit
        albedo (a dark surface gets a weak stripe, as a real one does).
    object_texture : str
        Procedural solid texture (:data:`OBJECT_TEXTURES`): ``blotches`` (smooth
        random patches), ``checker`` (3-D checker), ``stripes`` (horizontal bands);
        it blends ``object_albedo`` with ``object_albedo2``.
    object_albedo2 : (3,) float
        The texture's second colour.
    object_texture_scale : float, metres
        Size of the texture's features (checker square, band width, blotch size).
    specular, shininess : float
        Blinn-Phong highlight of the object (Blinn 1977): ``specular * max(0, n.h) **
        shininess`` in units of ``view_exposure_dn``, under the directional light (views
        and the room light of laser frames).
    laser_specular : float
        The same glint of the laser light (the stripe brightens where the object mirrors
        the laser toward the camera).
    table_tint : (3,) float
        RGB multiplier of the table's albedo.
    table_markers : str
        Printed dark pattern on the table (:data:`TABLE_MARKERS`): ``aruco`` (a grid of
        ArUco-like squares: black border, random 4 x 4 bits), ``checker``, ``dots``;
        none within ``marker_clearance`` of the object's footprint.
    marker_size, marker_pitch, marker_albedo, marker_clearance : float
        Marker (or checker square, or dot diameter) size and grid pitch (metres), ink
        albedo, free margin around the object (metres).
    wall_distance : float or None, metres
        A vertical wall at this horizontal distance from the origin (``None``: none),
        its inward normal toward azimuth ``wall_azimuth_deg + 180``; the laser line
        continues onto it.
    wall_azimuth_deg, wall_height, wall_albedo, wall_tint
        Where the wall stands (degrees from base +x), its height (m), albedo, tint.
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
    view_supersample: int = 4
    # ---- realism (issue 10); the defaults leave the demo cell exactly as it was
    laser_rgb: tuple[float, float, float] | None = None
    laser_ambient_fraction: float | None = None
    object_texture: str = "none"
    object_albedo2: tuple[float, float, float] = (0.25, 0.22, 0.20)
    object_texture_scale: float = 0.012
    specular: float = 0.0
    shininess: float = 60.0
    laser_specular: float = 0.0
    table_tint: tuple[float, float, float] = (1.08, 1.0, 0.9)
    table_markers: str = "none"
    marker_size: float = 0.02
    marker_pitch: float = 0.032
    marker_albedo: float = 0.05
    marker_clearance: float = 0.012
    wall_distance: float | None = None
    wall_azimuth_deg: float = 180.0
    wall_height: float = 0.5
    wall_albedo: float = 0.55
    wall_tint: tuple[float, float, float] = (1.0, 0.96, 0.88)

    def __post_init__(self) -> None:
        checks = [
            ("object_texture", self.object_texture in OBJECT_TEXTURES),
            ("table_markers", self.table_markers in TABLE_MARKERS),
            ("laser_rgb", self.laser_rgb is None or (len(self.laser_rgb) == 3
                                                     and min(self.laser_rgb) >= 0
                                                     and max(self.laser_rgb) > 0)),
            ("laser_ambient_fraction", self.laser_ambient_fraction is None
             or 0 <= self.laser_ambient_fraction <= 2),
            ("object_texture_scale", self.object_texture_scale > 0),
            ("specular", self.specular >= 0), ("laser_specular", self.laser_specular >= 0),
            ("shininess", self.shininess >= 1),
            ("marker_size", 0 < self.marker_size < self.marker_pitch),
            ("wall_distance", self.wall_distance is None or self.wall_distance > 0),
            ("wall_height", self.wall_height > 0),
            ("view_supersample", 1 <= self.view_supersample <= 16),
        ]
        for name, ok in checks:
            if not ok:
                raise ValueError(f"appearance parameter {name} out of range: "
                                 f"{getattr(self, name)!r}")

    @classmethod
    def cell(cls, laser: str | tuple[float, float, float] = "red",
             object_color: str | tuple[float, float, float] = "orange",
             texture: str = "blotches", markers: str = "aruco", wall: bool = True,
             **overrides: object) -> Appearance:
        """A cell as real ones are: room light, a coloured laser, a coloured textured
        glossy object on a bright marker table in front of a wall.

        Parameters
        ----------
        laser : {"red", "green", "blue"} or (3,) float
            The laser's colour as the RGB sensor sees it (:data:`LASER_RGB`).
        object_color : str or (3,) float
            A name of :data:`OBJECT_COLORS` or an RGB albedo.
        texture : str
            One of :data:`OBJECT_TEXTURES` (``none`` for a plain object).
        markers : str
            One of :data:`TABLE_MARKERS`.
        wall : bool
            A wall behind the table (0.40 m from the centre, at azimuth 180 degrees).
        **overrides
            Any other field.
        """
        rgb = LASER_RGB[laser] if isinstance(laser, str) else tuple(map(float, laser))
        if isinstance(laser, str) and laser not in LASER_RGB:
            raise ValueError(f"unknown laser colour {laser!r}; expected one of "
                             f"{', '.join(LASER_RGB)}")
        if isinstance(object_color, str):
            if object_color not in OBJECT_COLORS:
                raise ValueError(f"unknown object colour {object_color!r}; expected one of "
                                 f"{', '.join(OBJECT_COLORS)} or R G B")
            albedo = OBJECT_COLORS[object_color]
        else:
            albedo = tuple(float(x) for x in object_color)
        kw: dict[str, object] = dict(
            object_albedo=albedo,
            object_albedo2=tuple(round(0.45 * x, 4) for x in albedo),
            object_texture=texture, specular=0.35, shininess=40.0, laser_specular=0.25,
            table_albedo=0.82, table_texture=0.04, table_tint=(1.0, 0.99, 0.95),
            table_markers=markers, background=0.30, ambient=0.45, direct=0.55,
            view_exposure_dn=250.0, laser_rgb=rgb, laser_ambient_fraction=0.55,
            laser_peak_dn=320.0, laser_width=0.0006, wall_distance=0.40 if wall else None)
        kw.update(overrides)
        return cls(**kw)  # type: ignore[arg-type]


#: The fields of the demo cell's appearance (all others are issue 10's realism options).
LEGACY_FIELDS: tuple[str, ...] = (
    "object_albedo", "table_albedo", "table_texture", "background", "light_dir", "ambient",
    "direct", "view_exposure_dn", "laser_ambient_dn", "laser_peak_dn", "laser_width",
    "laser_fan_deg", "laser_reference_range", "supersample", "view_supersample")


@dataclass
class Hits:
    """First hits of a batch of rays.

    Attributes
    ----------
    kind : (N,) int8
        0 miss, 1 object, 2 table, 3 wall.
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


#: Half-size (metres) of the printed marker board: markers cover ``|x|, |y| <= 0.2``.
MARKER_BOARD_HALF = 0.2
_TEXTURE_WAVES = np.array([[0.83, 0.31, 0.46], [-0.27, 0.91, 0.31], [0.12, -0.45, 0.88],
                           [0.64, 0.64, -0.42], [-0.71, 0.05, 0.70]])
_TEXTURE_PHASES = np.array([0.3, 2.1, 4.0, 1.2, 5.3])


def object_texture_weight(points: np.ndarray, kind: str, scale: float) -> np.ndarray:
    """Weight ``(N,)`` in [0, 1] of the second colour of a procedural solid texture.

    Parameters
    ----------
    points : (N, 3) float64, metres
    kind : str
        One of :data:`OBJECT_TEXTURES`.
    scale : float, metres
        Feature size.
    """
    p = np.asarray(points, dtype=np.float64) / scale
    if kind == "none":
        return np.zeros(len(p))
    if kind == "checker":
        return (np.floor(p).astype(np.int64).sum(axis=1) % 2).astype(np.float64)
    if kind == "stripes":
        return (np.floor(p[:, 2]).astype(np.int64) % 2).astype(np.float64)
    # blotches: a sum of five plane waves, squashed to patches with soft edges
    w = np.sin(np.pi * (p @ _TEXTURE_WAVES.T) + _TEXTURE_PHASES).sum(axis=1)
    return 0.5 + 0.5 * np.tanh(1.6 * w)


def _hash_bits(*ints: np.ndarray) -> np.ndarray:
    """A deterministic pseudo-random bit per tuple of integer arrays."""
    h = np.zeros(np.broadcast(*ints).shape, dtype=np.uint64)
    for k, v in zip((73856093, 19349663, 83492791, 2654435761), ints, strict=False):
        h ^= v.astype(np.int64).astype(np.uint64) * np.uint64(k)
    h ^= h >> np.uint64(13)
    h *= np.uint64(1274126177)
    h ^= h >> np.uint64(16)
    return ((h >> np.uint64(7)) & np.uint64(1)).astype(bool)


def table_marker_ink(xy: np.ndarray, kind: str, size: float, pitch: float,
                     keep_out: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Where the table's printed pattern is dark: ``(N,)`` bool.

    Parameters
    ----------
    xy : (N, 2) float64, metres
        Table points.
    kind : str
        One of :data:`TABLE_MARKERS`: ``aruco`` (squares of ``size`` on a grid of
        ``pitch``, a black border of one cell of six and random 4 x 4 inner bits),
        ``checker`` (squares of ``size``), ``dots`` (discs of diameter ``size``).
    size, pitch : float, metres
    keep_out : ((2,), (2,)) float64
        A box ``(lo, hi)`` in x, y left blank (the object's footprint and margin).
    """
    xy = np.asarray(xy, dtype=np.float64)
    out = np.zeros(len(xy), dtype=bool)
    if kind == "none":
        return out
    cand = np.flatnonzero((np.abs(xy[:, 0]) <= MARKER_BOARD_HALF)
                          & (np.abs(xy[:, 1]) <= MARKER_BOARD_HALF))
    p = xy[cand]
    if kind == "checker":
        ij = np.floor(p / size).astype(np.int64)
        ink = (ij.sum(axis=1) % 2) == 0
        c_lo = ij * size
        c_hi = c_lo + size
    else:
        ij = np.floor(p / pitch).astype(np.int64)
        centre = (ij + 0.5) * pitch
        d = p - centre
        if kind == "dots":
            ink = np.einsum("ij,ij->i", d, d) <= (0.5 * size) ** 2
        else:
            ink = np.all(np.abs(d) < 0.5 * size, axis=1)
            k = np.flatnonzero(ink)  # bits only inside the squares
            b = np.clip(np.floor((d[k] + 0.5 * size) / (size / 6.0)).astype(np.int64), 0, 5)
            border = (b[:, 0] == 0) | (b[:, 0] == 5) | (b[:, 1] == 0) | (b[:, 1] == 5)
            ink[k] = border | _hash_bits(ij[k, 0], ij[k, 1], b[:, 0], b[:, 1])
        c_lo, c_hi = centre - 0.5 * size, centre + 0.5 * size
    lo, hi = keep_out
    clear = np.any(c_hi < lo, axis=1) | np.any(c_lo > hi, axis=1)
    out[cand] = ink & clear
    return out


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
    turntable : bool
        The object and the table turn on a turntable (``base`` turns with them) while
        the wall and the directional light stay in the room: the wall is placed in the
        room's frame, which :meth:`set_room_pose` moves in ``base`` frame by frame
        (identity: the room is ``base``, as without a turntable).
    """

    #: the wall's geometry id when it stands in the room (turntable), not in Open3D's scene
    _ROOM_WALL_ID = 1 << 30

    def __init__(self, mesh: TriangleMesh, appearance: Appearance | None = None,
                 table_half_size: float = 0.6, threads: int = 1,
                 turntable: bool = False) -> None:
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
        a = self.appearance
        self._wall_id: int | None = None
        self._wall_normal = np.zeros(3)
        self._wall_tangent = np.zeros(3)
        self._room: tuple[np.ndarray, np.ndarray] | None = None  # (R, t): room -> base
        self._room_wall: dict[str, Any] | None = None
        if a.wall_distance is not None:  # a vertical quad facing the origin
            az = np.radians(a.wall_azimuth_deg)
            out = np.array([np.cos(az), np.sin(az), 0.0])
            tangent = np.array([-out[1], out[0], 0.0])
            c = a.wall_distance * out
            self._wall_normal = -out
            self._wall_tangent = tangent
            if turntable:  # in the room, down past the turntable's plate, cast by hand
                self._wall_id = self._ROOM_WALL_ID
                self._room_wall = {"centre": c, "normal": -out, "tangent": tangent,
                                   "half_width": s, "z": (-0.5, a.wall_height)}
            else:
                wv = np.array([c - s * tangent, c + s * tangent,
                               c + s * tangent + [0, 0, a.wall_height],
                               c - s * tangent + [0, 0, a.wall_height]], dtype=np.float32)
                self._wall_id = self._scene.add_triangles(o3d.core.Tensor(wv),
                                                          o3d.core.Tensor(tf))
        self.turntable = bool(turntable)
        lo, hi = mesh.bounds
        self._keep_out = (lo[:2] - a.marker_clearance, hi[:2] + a.marker_clearance)
        self._vertex_normals = mesh.vertex_normals()
        self._faces = mesh.faces
        self._ray_cache: dict[tuple, np.ndarray] = {}

    # ------------------------------------------------------------------ the room
    def set_room_pose(self, T_base_room: np.ndarray | None) -> None:
        """Where the room (the wall and the directional light of a turntable scene)
        stands in ``base`` for the frames rendered next: ``T_base_room`` (4, 4), the
        turntable's turn undone; None for the room at rest in ``base``."""
        if T_base_room is None:
            self._room = None
        else:
            T = np.asarray(T_base_room, dtype=np.float64)
            self._room = (T[:3, :3].copy(), T[:3, 3].copy())
        if self._room_wall is not None:
            R = np.eye(3) if self._room is None else self._room[0]
            self._wall_normal = R @ self._room_wall["normal"]
            self._wall_tangent = R @ self._room_wall["tangent"]

    def light_direction(self) -> np.ndarray:
        """Unit direction toward the directional light in ``base`` (the room's light,
        turned with the room on a turntable)."""
        light = np.asarray(self.appearance.light_dir, dtype=np.float64)
        if self.turntable and self._room is not None:
            light = self._room[0] @ light
        return light / np.linalg.norm(light)

    def _to_room(self, points: np.ndarray) -> np.ndarray:
        if self._room is None:
            return points
        R, t = self._room
        return (points - t) @ R

    # ------------------------------------------------------------------ casting
    def _cast_raw(self, origins: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        rays = np.empty((len(dirs), 6), dtype=np.float32)
        rays[:, :3] = origins
        rays[:, 3:] = dirs
        out = self._scene.cast_rays(self._o3d.core.Tensor(rays), nthreads=self.threads)
        out = {k: v.numpy() for k, v in out.items()}
        if self._room_wall is not None:  # the room's wall: a plane, bounded, by hand
            w = self._room_wall
            o = self._to_room(np.broadcast_to(np.asarray(origins, np.float64), dirs.shape))
            d = np.asarray(dirs, np.float64) if self._room is None else \
                np.asarray(dirs, np.float64) @ self._room[0]
            dn = d @ w["normal"]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = ((w["centre"] - o) @ w["normal"]) / dn
            x = o + np.where(np.isfinite(t), t, 0.0)[:, None] * d
            inside = (np.isfinite(t) & (t > 0) & (dn < 0)
                      & (np.abs((x - w["centre"]) @ w["tangent"]) <= w["half_width"])
                      & (x[:, 2] >= w["z"][0]) & (x[:, 2] <= w["z"][1]))
            hit = inside & (t < out["t_hit"])
            out["t_hit"] = np.where(hit, t, out["t_hit"]).astype(out["t_hit"].dtype)
            out["geometry_ids"] = np.where(hit, self._ROOM_WALL_ID, out["geometry_ids"])
        return out

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
        if self._wall_id is not None:
            kind[gid == self._wall_id] = WALL
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
            normals_[kind == WALL] = self._wall_normal
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
        lut = np.array([0.0, float(np.mean(a.object_albedo)), a.table_albedo, a.wall_albedo])
        out = lut[hits.kind]
        if texture and a.table_texture:
            table = hits.kind == TABLE
            out[table] *= 1 + a.table_texture * _table_pattern(hits.points[table])
        return out

    def albedo_rgb(self, hits: Hits) -> np.ndarray:
        """RGB albedo ``(N, 3)`` at the hits (0 on a miss)."""
        a = self.appearance
        out = np.zeros((len(hits.kind), 3))
        obj = np.flatnonzero(hits.kind == OBJECT)
        out[obj] = a.object_albedo
        if a.object_texture != "none" and len(obj):
            wt = object_texture_weight(hits.points[obj], a.object_texture,
                                       a.object_texture_scale)[:, None]
            out[obj] = (1 - wt) * np.asarray(a.object_albedo) + wt * np.asarray(a.object_albedo2)
        table = np.flatnonzero(hits.kind == TABLE)
        table_pts = hits.points[table]
        grain = a.table_albedo * (1 + a.table_texture * _table_pattern(table_pts))
        out[table] = grain[:, None] * np.array(a.table_tint)
        if a.table_markers != "none" and len(table):
            ink = table_marker_ink(table_pts[:, :2], a.table_markers, a.marker_size,
                                   a.marker_pitch, self._keep_out)
            out[table[ink]] = a.marker_albedo
        wall = hits.kind == WALL
        if self._wall_id is not None and np.any(wall):
            pw = self._to_room(hits.points[wall]) if self._room_wall is not None else \
                hits.points[wall]
            tangent = (self._room_wall["tangent"] if self._room_wall is not None
                       else self._wall_tangent)
            st = np.stack([pw @ tangent, pw[:, 2]], axis=1)
            plaster = a.wall_albedo * (1 + 0.08 * _table_pattern(0.3 * st))
            out[wall] = plaster[:, None] * np.asarray(a.wall_tint)
        return out

    def albedo_at_laser(self, hits: Hits) -> np.ndarray:
        """Albedo ``(N,)`` at the laser's wavelength: the RGB albedo's channel where the
        laser is strongest (the mean of the channels for a grey laser)."""
        rgb = self.albedo_rgb(hits)
        a = self.appearance
        if a.laser_rgb is None:
            return rgb.mean(axis=1)
        return rgb[:, int(np.argmax(a.laser_rgb))]

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


def render_view(scene: SimScene, camera: CameraModel, T_base_camera: np.ndarray, *,
                return_silhouette: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Noise-free ambient-lit view of the scene.

    Parameters
    ----------
    scene : SimScene
    camera : CameraModel
    T_base_camera : (4, 4) float64
    return_silhouette : bool
        Also return the true silhouette: the pixels whose centre ray hits the object.

    Returns
    -------
    (H, W, 3) float64, DN
        RGB signal before sensor noise.
    silhouette : (H, W) bool
        Only with ``return_silhouette``.
    """
    rgb, hits = _view_signal(scene, camera, T_base_camera)
    image = rgb.reshape(camera.height, camera.width, 3)
    if return_silhouette:
        return image, (hits.kind == OBJECT).reshape(camera.height, camera.width)
    return image


def _view_signal(scene: SimScene, camera: CameraModel,
                 T_base_camera: np.ndarray) -> tuple[np.ndarray, Hits]:
    """The view's RGB signal ``(H * W, 3)`` (DN) and the pixel-centre hits.

    Pixels on a geometric edge (a neighbour's centre ray hits another surface, or the
    same one at a depth differing by more than :data:`_EDGE_DEPTH_REL`) are the mean of
    ``view_supersample x view_supersample`` rays over their area, as a sensor integrates
    them: an outline rendered at pixel centres alone is a staircase whose gradient peak
    lies about a tenth of a pixel off the true edge on average (stop 23)."""
    a = scene.appearance
    t = np.asarray(T_base_camera, dtype=np.float64)
    dirs = scene.pixel_rays(camera) @ t[:3, :3].T
    rgb, hits = _shade(scene, t[:3, 3], dirs)
    n = int(a.view_supersample)
    if n > 1:
        idx = _edge_pixels(hits, camera.height, camera.width)
        if len(idx):
            w = camera.width
            sub_rgb, _ = _shade(scene, t[:3, 3], camera.rays(_subpixels(idx, w, n)) @ t[:3, :3].T)
            rgb[idx] = sub_rgb.reshape(len(idx), n * n, 3).mean(axis=1)
    return rgb * a.view_exposure_dn, hits


def _subpixels(idx: np.ndarray, width: int, n: int) -> np.ndarray:
    """``(len(idx) * n * n, 2)`` sub-pixel positions: an ``n x n`` grid over the area of
    each pixel of the flat indices ``idx`` (row-major, image ``width``), pixel by pixel."""
    offs = (np.arange(n) + 0.5) / n - 0.5
    du, dv = np.meshgrid(offs, offs)
    uv = np.stack([idx % width, idx // width], axis=1).astype(np.float64)
    return (uv[:, None, :] + np.stack([du.ravel(), dv.ravel()], axis=1)[None]).reshape(-1, 2)


#: Relative depth jump between neighbouring pixel centres that marks an occluding edge
_EDGE_DEPTH_REL = 0.02


def _edge_pixels(hits: Hits, h: int, w: int) -> np.ndarray:
    """Flat indices of the pixels on a geometric edge: a 4-neighbour's centre ray hits
    another surface, or the same at a relative depth jump above :data:`_EDGE_DEPTH_REL`."""
    kind = hits.kind.reshape(h, w)
    depth = np.where(np.isfinite(hits.t), hits.t, 0.0).reshape(h, w)
    edge = np.zeros((h, w), dtype=bool)
    for a_, b_ in (((slice(None), slice(1, None)), (slice(None), slice(None, -1))),
                   ((slice(1, None), slice(None)), (slice(None, -1), slice(None)))):
        ka, kb, da, db = kind[a_], kind[b_], depth[a_], depth[b_]
        jump = (ka != kb) | (np.abs(da - db) > _EDGE_DEPTH_REL * np.maximum(da, db))
        edge[a_] |= jump
        edge[b_] |= jump
    return np.flatnonzero(edge)


def _shade(scene: SimScene, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, Hits]:
    """RGB radiance ``(N, 3)`` (units of ``view_exposure_dn``) of the rays ``dirs`` from
    ``origin`` under the views' light, and their hits."""
    a = scene.appearance
    hits = scene.cast(origin, dirs)
    light = scene.light_direction()
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
    if a.specular > 0:  # Blinn-Phong glint of the directional light on the object
        obj = np.flatnonzero((hits.kind == OBJECT) & (shade > 0))
        half = light - dirs[obj]
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        nh = np.maximum(np.einsum("ij,ij->i", hits.normals[obj], half), 0.0)
        rgb[obj] += (a.specular * a.direct * nh ** a.shininess)[:, None]
    rgb[~hit] = a.background
    return rgb, hits


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
                       T_base_laser: np.ndarray, laser_gain: np.ndarray | None = None
                       ) -> np.ndarray:
    """Noise-free laser-lit frame (dimmed ambient plus the stripe).

    Parameters
    ----------
    scene : SimScene
    camera : CameraModel
    T_base_camera : (4, 4) float64
    T_base_laser : (4, 4) float64
        The laser frame in ``base``; the sheet is its x-z plane.
    laser_gain : (H, W) float64, optional
        A factor on the laser's light per pixel, the room light's unchanged: its speckle
        (:func:`speckle_gain`). None: none (the frame as before, to the last bit).

    Returns
    -------
    (H, W) or (H, W, 3) float64, DN
        Grey signal before sensor noise; RGB when ``appearance.laser_rgb`` is set. With
        ``appearance.laser_ambient_fraction`` the room light is the view's rendering
        times that fraction (see :class:`Appearance`).
    """
    a = scene.appearance
    t = np.asarray(T_base_camera, dtype=np.float64)
    t_l = np.asarray(T_base_laser, dtype=np.float64)
    if a.laser_rgb is not None or a.laser_ambient_fraction is not None:
        return _render_laser_frame_lit(scene, camera, t, t_l, laser_gain)
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
    sub_dirs = camera.rays(_subpixels(idx, w, s)) @ t[:3, :3].T
    sub = scene.cast(t[:3, 3], sub_dirs)
    room = scene.albedo_grey(sub, texture=False) * ambient
    las = _laser_dn(scene, sub, t_l)
    if laser_gain is None:
        image[idx] = (room + las).reshape(len(idx), s * s).mean(axis=1)
    else:
        image[idx] = (room.reshape(len(idx), s * s).mean(axis=1)
                      + las.reshape(len(idx), s * s).mean(axis=1) * laser_gain.reshape(-1)[idx])
    return image.reshape(h, w)


def _stripe_pixels(scene: SimScene, camera: CameraModel, hits: Hits,
                   t_l: np.ndarray) -> np.ndarray:
    """Flat indices of the pixels to supersample: centre hit near the sheet, dilated."""
    a = scene.appearance
    h, w = camera.height, camera.width
    d = np.abs((hits.points - t_l[:3, 3]) @ t_l[:3, 1])
    footprint = np.where(np.isfinite(hits.t), hits.t, 0.0) / camera.fx
    near = (hits.kind != MISS) & (d < 2.0 * a.laser_width + 1.0 * footprint)
    near = cv2.dilate(near.reshape(h, w).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    return np.flatnonzero(near)


def _laser_dn_lit(scene: SimScene, hits: Hits, T_base_laser: np.ndarray,
                  view_dirs: np.ndarray) -> np.ndarray:
    """Laser-lit DN ``(N,)`` of hit points in a room-lit / coloured-laser frame.

    ``laser_peak_dn`` per unit albedo at the laser's wavelength, times the sheet's
    Gaussian profile, ``cos(theta)`` and ``r_ref / r``; plus the laser's Blinn-Phong
    glint on the object (``laser_specular``); zero where the laser is shadowed.
    """
    a = scene.appearance
    out = np.zeros(len(hits.kind))
    o = T_base_laser[:3, 3]
    p_l = (hits.points - o) @ T_base_laser[:3, :3]
    gauss = np.exp(-2.0 * (p_l[:, 1] / a.laser_width) ** 2)
    in_fan = (p_l[:, 2] > 0) & (np.abs(np.arctan2(p_l[:, 0], p_l[:, 2]))
                                <= np.radians(a.laser_fan_deg))
    cand = np.nonzero((hits.kind != MISS) & in_fan & (gauss > 1e-6))[0]
    if len(cand) == 0:
        return out
    vec = hits.points[cand] - o
    rng_ = np.linalg.norm(vec, axis=1)
    n = hits.normals[cand]
    cos = np.maximum(-np.einsum("ij,ij->i", n, vec) / rng_, 0.0)
    lit = scene.first_hit_distance(o, vec) >= 1.0 - 5e-5 / rng_
    sub = Hits(hits.kind[cand], hits.t[cand], hits.points[cand], n)
    albedo = scene.albedo_at_laser(sub)
    value = albedo * cos
    if a.laser_specular > 0:
        half = -vec / rng_[:, None] - view_dirs[cand]
        half /= np.linalg.norm(half, axis=1, keepdims=True)
        nh = np.maximum(np.einsum("ij,ij->i", n, half), 0.0)
        value = value + np.where(sub.kind == OBJECT, a.laser_specular * nh ** a.shininess, 0.0)
    out[cand] = a.laser_peak_dn * value * gauss[cand] * (a.laser_reference_range / rng_) * lit
    return out


def _render_laser_frame_lit(scene: SimScene, camera: CameraModel, t: np.ndarray,
                            t_l: np.ndarray, laser_gain: np.ndarray | None = None
                            ) -> np.ndarray:
    """A laser frame in room light and/or with a coloured laser (see render_laser_frame).

    The room light is the view's rendering (:func:`_view_signal`: pixel centres,
    supersampled on geometric edges); the laser is added as the mean over
    ``supersample x supersample`` rays of the pixels near the sheet.
    """
    a = scene.appearance
    h, w = camera.height, camera.width
    if a.laser_ambient_fraction is not None:
        room, hits = _view_signal(scene, camera, t)
        room *= a.laser_ambient_fraction
    else:
        dirs = scene.pixel_rays(camera) @ t[:3, :3].T
        hits = scene.cast(t[:3, 3], dirs, normals=False)
        room = scene.albedo_rgb(hits) * (a.laser_ambient_dn / float(np.mean(a.object_albedo)))
    idx = _stripe_pixels(scene, camera, hits, t_l)
    laser = np.zeros(h * w)
    if len(idx):
        s = max(int(a.supersample), 1)
        sub_dirs = camera.rays(_subpixels(idx, w, s)) @ t[:3, :3].T
        sub = scene.cast(t[:3, 3], sub_dirs)
        laser[idx] = _laser_dn_lit(scene, sub, t_l, sub_dirs).reshape(len(idx), s * s).mean(1)
    if laser_gain is not None:
        laser *= laser_gain.reshape(-1)
    if a.laser_rgb is None:
        return (room.mean(axis=1) + laser).reshape(h, w)
    colour = np.asarray(a.laser_rgb, dtype=np.float64)
    return (room + laser[:, None] * colour).reshape(h, w, 3)


class StripeTruth(NamedTuple):
    """The true laser stripe of one frame (:func:`visible_stripe_points`).

    Attributes
    ----------
    points_base : (N, 3) float64, metres
        Surface points on the laser sheet, lit by the laser and seen by the camera, in
        the order of the laser's fan angle (a connected curve between depth jumps).
    pixels_uv : (N, 2) float64
        Their (distorted) pixels, inside the image.
    on_object : (N,) bool
        On the object (else on the table or the wall).
    kind : (N,) int8
        1 object, 2 table, 3 wall.
    signal_dn : (N,) float64
        The stripe's expected peak signal there (DN above the room light, before the
        sensor clips it), as the renderer computes it: the laser's incidence, the albedo,
        the range, and the pixel's average of the line's profile (a surface the camera
        sees nearly edge-on records a fraction of the peak:
        :func:`_pixel_footprint_factor`); a benchmark may ignore points too faint to be
        seen (grazing incidence, grazing view, dark surfaces).
    """

    points_base: np.ndarray
    pixels_uv: np.ndarray
    on_object: np.ndarray
    kind: np.ndarray
    signal_dn: np.ndarray


def visible_stripe_points(scene: SimScene, camera: CameraModel, T_base_camera: np.ndarray,
                          T_base_laser: np.ndarray, n_rays: int | None = None
                          ) -> StripeTruth:
    """The truth of a laser frame's stripe: where the sheet lights the scene and the
    camera sees it.

    Rays are cast from the laser's origin in its sheet (the x-z plane of the laser
    frame) over the fan, ``n_rays`` evenly spaced in angle; their first hits are the lit
    points (the laser's own shadowing is exact). A point is kept when the camera's ray
    toward it first hits the point itself (not occluded), it is in front of the camera
    and its projection falls inside the image.

    Parameters
    ----------
    scene : SimScene
    camera : CameraModel
    T_base_camera, T_base_laser : (4, 4) float64
        The TRUE poses at the frame's exposure (a recording's ground truth: see
        ``ground_truth/image_poses.json`` in ``recordings/README.md``).
    n_rays : int, optional
        Rays over the fan (default ``8 * max(width, height)``: a few tenths of a pixel
        apart in the image at the working distance).

    Returns
    -------
    StripeTruth
    """
    a = scene.appearance
    t = np.asarray(T_base_camera, dtype=np.float64)
    t_l = np.asarray(T_base_laser, dtype=np.float64)
    n = int(n_rays) if n_rays is not None else 8 * max(camera.width, camera.height)
    if n < 2:
        raise ValueError(f"n_rays must be >= 2, got {n}")
    ang = np.radians(a.laser_fan_deg) * np.linspace(-1.0, 1.0, n)
    dirs_l = np.stack([np.sin(ang), np.zeros(n), np.cos(ang)], axis=1)
    o = t_l[:3, 3]
    hits = scene.cast(o, dirs_l @ t_l[:3, :3].T)
    keep = np.flatnonzero(hits.kind != MISS)
    pts = hits.points[keep]
    c = t[:3, 3]
    vec = pts - c
    dist = np.linalg.norm(vec, axis=1)
    seen = scene.first_hit_distance(c, vec) >= 1.0 - 5e-5 / np.maximum(dist, 1e-9)
    p_cam = (pts - c) @ t[:3, :3]
    uv, front = camera.project(p_cam)
    inside = (front & (uv[:, 0] >= -0.5) & (uv[:, 0] <= camera.width - 0.5)
              & (uv[:, 1] >= -0.5) & (uv[:, 1] <= camera.height - 0.5))
    ok = seen & inside
    keep, pts, uv = keep[ok], pts[ok], uv[ok]
    kind = hits.kind[keep]
    sub = Hits(kind, hits.t[keep], pts, hits.normals[keep])
    vec_l = pts - o
    rng_ = np.linalg.norm(vec_l, axis=1)
    cos = np.maximum(-np.einsum("ij,ij->i", sub.normals, vec_l) / rng_, 0.0)
    if a.laser_rgb is None and a.laser_ambient_fraction is None:
        albedo = scene.albedo_grey(sub) / float(np.mean(a.object_albedo))
    else:
        albedo = scene.albedo_at_laser(sub)
    signal = (a.laser_peak_dn * albedo * cos * (a.laser_reference_range / rng_)
              * _pixel_footprint_factor(camera, t, pts, sub.normals, t_l[:3, 1], uv,
                                        a.laser_width))
    return StripeTruth(pts, uv, kind == OBJECT, kind.astype(np.int8), signal)


def _pixel_footprint_factor(camera: CameraModel, T_base_camera: np.ndarray,
                            points: np.ndarray, normals: np.ndarray, sheet_normal: np.ndarray,
                            uv: np.ndarray, width: float) -> np.ndarray:
    """The share of the sheet's peak that the pixel on the stripe records (N,): the
    sheet's profile ``exp(-2 (y / width)^2)`` averaged over the pixel.

    ``y`` (the distance from the sheet) changes across the image by ``|grad y|`` metres
    per pixel, from the surface's tangent plane and the camera's projection (distortion
    included; a 2 x 2 Jacobian per point, by finite differences of 10 um). Where the
    camera sees the lit surface nearly edge-on, or the sheet meets it at a grazing angle,
    the line's image is narrower than a pixel and the pixel averages it with the dark
    around it: a one-pixel box over the Gaussian gives
    ``(w / D) sqrt(pi / 2) erf(D / (sqrt(2) w))``, D = ``|grad y|`` x 1 px (1 when D << w,
    0 for a surface seen exactly edge-on).
    """
    from scipy.special import erf

    n = np.asarray(normals, dtype=np.float64)
    if len(n) == 0:
        return np.zeros(0)
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    t1 = np.cross(n, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    eps = 1e-5
    R, c = T_base_camera[:3, :3], T_base_camera[:3, 3]
    uv1, _ = camera.project((points + eps * t1 - c) @ R)
    uv2, _ = camera.project((points + eps * t2 - c) @ R)
    # J[:, :, k] = d(uv) / d(s_k) along tangent k; dy = g . ds, so grad_uv y = J^-T g
    j11, j21 = (uv1 - uv).T / eps
    j12, j22 = (uv2 - uv).T / eps
    g1, g2 = t1 @ sheet_normal, t2 @ sheet_normal
    det = j11 * j22 - j12 * j21
    ok = np.abs(det) > 1e-12 * (np.abs(j11 * j22) + np.abs(j12 * j21) + 1e-300)
    d = np.where(ok, det, 1.0)
    # J^-T = [[j22, -j21], [-j12, j11]] / det
    gu = (j22 * g1 - j21 * g2) / d
    gv = (-j12 * g1 + j11 * g2) / d
    D = np.hypot(gu, gv)
    w = float(width)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = np.where(D > 1e-6 * w, (w / D) * np.sqrt(np.pi / 2) * erf(D / (np.sqrt(2) * w)),
                     1.0)
    return np.where(ok, np.clip(f, 0.0, 1.0), 0.0)


def sensor_noise(signal_dn: np.ndarray, rng: np.random.Generator, gain: float,
                 read_noise: float, gaussian_shot: bool = False) -> np.ndarray:
    """Add shot and read noise to a signal and quantise it to 8 bits.

    Parameters
    ----------
    signal_dn : (H, W) or (H, W, 3) float64, DN
    rng : numpy Generator
    gain : float, DN per electron
        Shot noise: the signal is ``gain * Poisson(signal / gain)`` (0: none).
    read_noise : float, DN
        Standard deviation of Gaussian read noise.
    gaussian_shot : bool
        Draw shot and read noise from one normal (variance ``gain * signal +
        read_noise^2``), about three times faster; exact enough above a few tens of
        electrons, which a
        room-lit image has everywhere but in its darkest shadows.

    Returns
    -------
    uint8 array of the same shape
    """
    s = np.maximum(np.asarray(signal_dn, dtype=np.float64), 0.0)
    if gaussian_shot:  # shot and read noise in one normal draw
        sigma = np.sqrt(np.float32(gain) * s.astype(np.float32) + np.float32(read_noise) ** 2)
        s = s + sigma * rng.standard_normal(s.shape, dtype=np.float32)
        return np.clip(np.rint(s), 0, 255).astype(np.uint8)
    if gain > 0:
        s = rng.poisson(s / gain) * gain
    if read_noise > 0:
        s = s + rng.normal(0.0, read_noise, s.shape)
    return np.clip(np.rint(s), 0, 255).astype(np.uint8)


def vignetting(height: int, width: int, strength: float) -> np.ndarray:
    """A lens's vignetting, ``(H, W)`` gain: ``1 - strength * (r / r_corner)^2`` (a
    cheap lens's light fall-off; ``strength`` 0.2-0.35 loses 20-35 % in the corners)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    r2 = ((u - (width - 1) / 2) ** 2 + (v - (height - 1) / 2) ** 2)
    return 1.0 - strength * r2 / r2.max()


def speckle_gain(height: int, width: int, contrast: float, grain_px: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Laser speckle: a random ``(H, W)`` factor on the laser's light, mean 1, standard
    deviation ``contrast``, correlated over about ``grain_px`` pixels.

    A laser's coherent light scattered by a rough surface interferes with itself: the
    stripe's brightness varies from one speckle grain to the next (Goodman 1975), and its
    centre of gravity moves with the grains, the fundamental limit of laser triangulation
    (Dorsch, Häusler & Herrmann 1994). Fully developed speckle (``contrast`` 1) has an
    exponential intensity, the squared modulus of a complex Gaussian field (here white
    noise blurred by a Gaussian of ``grain_px / 2`` px); a pixel larger than the grain, or
    a wide aperture, averages several patterns: ``m = round(1 / contrast^2)`` of them,
    their mean's deviation scaled to ``contrast`` (0.3-0.6 for a webcam's pixels and
    lens, up to 1 behind a small machine-vision aperture). ``contrast`` 0: all ones.
    """
    if contrast <= 0:
        return np.ones((height, width))
    m = max(1, int(round(1.0 / contrast ** 2)))
    sigma = max(grain_px, 1e-3) / 2.0
    acc = np.zeros((height, width))
    for _ in range(m):
        re, im = (cv2.GaussianBlur(rng.standard_normal((height, width)), (0, 0), sigma,
                                   borderType=cv2.BORDER_REFLECT) for _ in range(2))
        intensity = re * re + im * im
        acc += intensity / intensity.mean()
    pattern = acc / m  # mean 1, deviation about 1 / sqrt(m)
    return np.maximum(1.0 + contrast * np.sqrt(m) * (pattern - 1.0), 0.0)
