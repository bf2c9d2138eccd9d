"""Ground-truth objects of the simulator: signed distance functions, meshed and decimated.

Every object is a closed triangle mesh in the ``base`` frame (metres), resting on the
table plane ``z = 0`` and centred near the origin. The mesh returned here *is* the
ground truth: the simulator renders from exactly these (float32-rounded) vertices and
writes the same vertices into the ``ground_truth/mesh.ply`` attachment.

Objects
-------
``dimple_block``
    A 100 x 80 x 60 mm rounded block with three concavities a visual hull cannot see:
    a spherical dimple (11 mm deep) and a blind groove (6 mm) in the top face, and a
    rounded rectangular pocket (12 mm deep) in its ``-y`` face.
``vase``
    A 110 mm tall surface of revolution with a belly and a waist, modulated by three
    lobes that twist with height (so it has no rotational symmetry for registration to
    slide along), with a shallow dish in its top.
``blob``
    A smooth potato: a sphere perturbed by low-order harmonics, flattened where it rests.
``bracket``
    A flat-faced L bracket of 6 mm plate (90 x 60 mm foot, 50 mm upright) with a groove
    across its foot and three through-holes (two in the foot, one in the upright): the
    visual hull closes the holes, the laser sees their walls only in part.
``cup``
    A thin-walled cup (2.5 mm wall, 70 mm wide, 85 mm tall) with a loop handle and an
    open top: a deep concavity that the visual hull closes across the opening.
``bumpy_blob``
    ``blob``'s potato with 28 bumps and dents of 1.5-3.5 mm, 5-9 mm wide.
``near_symmetric``
    A bottle that is almost a surface of revolution (2 % elliptic, slightly tapered)
    with one small boss: registration has one nearly unconstrained rotation.
``thin_wall``
    A 1.8 mm fin, 60 mm tall, standing on a block, with a 1.5 mm gusset.
``sphere``
    A 40 mm radius sphere touching the table at the origin, as a subdivided icosahedron
    whose vertices lie exactly on the sphere (facet sagitta about 15 micrometres), so
    tests may use the analytic sphere.

Choices
-------
- SDF objects are meshed with marching cubes (Lewiner et al. 2003) on a grid of
  ``voxel`` metres (0.6 mm by default) and decimated with quadric edge collapse
  (Garland & Heckbert 1997, pymeshlab) to ``faces`` triangles (40 000 by default,
  about 0.7 MB as binary PLY), preserving normals and planar regions.
- The SDFs of surfaces of revolution are first-order approximations (distance along the
  profile normal); only their zero level set matters for the truth, and it is exact.
- After meshing, the mesh is shifted so that its lowest vertex is at ``z = 0`` exactly.

References
----------
Lewiner, T., Lopes, H., Vieira, A. W., Tavares, G. (2003). Efficient implementation of
marching cubes' cases with topological guarantees. Journal of Graphics Tools 8(2).

Garland, M., Heckbert, P. S. (1997). Surface simplification using quadric error metrics.
SIGGRAPH '97.

Quilez, I. Distance functions (smooth minimum, rounded boxes), iquilezles.org.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = [
    "TriangleMesh",
    "OBJECTS",
    "make_object",
    "mesh_sdf",
    "decimate_mesh",
    "icosphere",
    "mesh_to_ply_bytes",
    "sdf_dimple_block",
    "sdf_vase",
    "sdf_blob",
    "sdf_bracket",
    "sdf_cup",
    "sdf_bumpy_blob",
    "sdf_near_symmetric",
    "sdf_thin_wall",
]

_log = logging.getLogger(__name__)

Sdf = Callable[[np.ndarray], np.ndarray]


@dataclass(frozen=True)
class TriangleMesh:
    """A closed triangle mesh.

    Attributes
    ----------
    vertices : (V, 3) float64, metres
        Vertex positions (exactly representable in float32).
    faces : (F, 3) int64
        Vertex indices of each triangle, counter-clockwise seen from outside.
    """

    vertices: np.ndarray
    faces: np.ndarray

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned bounding box ``(min (3,), max (3,))`` in metres."""
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def vertex_normals(self) -> np.ndarray:
        """Area-weighted unit vertex normals ``(V, 3)``."""
        v, f = self.vertices, self.faces
        fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        vn = np.zeros_like(v)
        for k in range(3):
            np.add.at(vn, f[:, k], fn)
        n = np.linalg.norm(vn, axis=1, keepdims=True)
        return vn / np.where(n > 0, n, 1.0)

    def volume(self) -> float:
        """Signed volume (m^3), positive for outward-oriented faces."""
        v = self.vertices[self.faces]
        return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


# --------------------------------------------------------------------------- SDF primitives
def _smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth maximum (rounded intersection / subtraction) of width ``k``."""
    if k <= 0:
        return np.maximum(a, b)
    h = np.clip(0.5 - 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h + k * h * (1.0 - h)


def _round_box(p: np.ndarray, centre: tuple[float, float, float],
               half: tuple[float, float, float], radius: float) -> np.ndarray:
    q = np.abs(p - np.asarray(centre, dtype=p.dtype)) - (np.asarray(half, dtype=p.dtype) - radius)
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(q.max(axis=-1), 0.0)
    return outside + inside - radius


def _sphere(p: np.ndarray, centre: tuple[float, float, float], radius: float) -> np.ndarray:
    return np.linalg.norm(p - np.asarray(centre, dtype=p.dtype), axis=-1) - radius


def _capsule(p: np.ndarray, a: tuple[float, float, float], b: tuple[float, float, float],
             radius: float) -> np.ndarray:
    a_ = np.asarray(a, dtype=p.dtype)
    ba = np.asarray(b, dtype=p.dtype) - a_
    pa = p - a_
    h = np.clip((pa @ ba) / float(ba @ ba), 0.0, 1.0)
    return np.linalg.norm(pa - h[..., None] * ba, axis=-1) - radius


def _rounded_intersection(a: np.ndarray, b: np.ndarray, radius: float) -> np.ndarray:
    """Intersection of two SDFs with the edge rounded by ``radius`` (exact for planes)."""
    qa, qb = a + radius, b + radius
    outside = np.sqrt(np.maximum(qa, 0.0) ** 2 + np.maximum(qb, 0.0) ** 2)
    return outside + np.minimum(np.maximum(qa, qb), 0.0) - radius


# --------------------------------------------------------------------------- objects
def sdf_dimple_block(p: np.ndarray) -> np.ndarray:
    """SDF of ``dimple_block`` at points ``(..., 3)`` (metres); negative inside."""
    top = 0.06
    d = _round_box(p, (0.0, 0.0, 0.03), (0.05, 0.04, 0.03), 0.008)
    k = 0.0015
    # spherical dimple, 11 mm deep, rim radius 19 mm
    d = _smax(d, -_sphere(p, (-0.018, 0.0, top + 0.022 - 0.011), 0.022), k)
    # blind groove along y in the top face, 6 mm radius, ends 15 mm inside the faces
    d = _smax(d, -_capsule(p, (0.028, -0.022, top), (0.028, 0.022, top), 0.006), k)
    # rounded pocket in the -y face: 30 x 20 mm, 12 mm deep
    d = _smax(d, -_round_box(p, (0.018, -0.04, 0.03), (0.015, 0.012, 0.010), 0.004), k)
    return d


_VASE_H = 0.11
_VASE_Z = np.array([0.0, 0.02, 0.045, 0.075, 0.095, 0.11])
_VASE_R = np.array([0.032, 0.043, 0.046, 0.027, 0.029, 0.034])


def sdf_vase(p: np.ndarray) -> np.ndarray:
    """SDF (first order) of ``vase`` at points ``(..., 3)`` (metres); negative inside."""
    from scipy.interpolate import PchipInterpolator

    profile = PchipInterpolator(_VASE_Z, _VASE_R, extrapolate=True)
    dprofile = profile.derivative()
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    zc = np.clip(z, 0.0, _VASE_H)
    rho = np.hypot(x, y)
    phi = np.arctan2(y, x)
    twist = 1.2 * zc / _VASE_H
    lobes = 1.0 + 0.07 * np.cos(3.0 * (phi - twist)) * (0.5 + 0.5 * np.sin(np.pi * zc / _VASE_H))
    r = profile(zc) * lobes
    slope = dprofile(zc) * lobes
    side = (rho - r) / np.sqrt(1.0 + slope * slope)
    slab = np.maximum(-z, z - _VASE_H)
    d = _rounded_intersection(side, slab, 0.003)
    # shallow dish in the top: 6 mm deep
    d = _smax(d, -_sphere(p, (0.0, 0.0, _VASE_H + 0.06 - 0.006), 0.06), 0.002)
    return d


def sdf_blob(p: np.ndarray) -> np.ndarray:
    """SDF (first order) of ``blob`` at points ``(..., 3)`` (metres); negative inside."""
    c = np.array([0.0, 0.0, 0.040], dtype=p.dtype)
    q = p - c
    r = np.linalg.norm(q, axis=-1)
    u = q / np.maximum(r, 1e-9)[..., None]
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    radius = 0.046 * (1.0 + 0.16 * ux * uy + 0.12 * (uz * uz - 0.33) + 0.09 * ux
                      - 0.07 * uy * uz + 0.05 * (ux**3 - 3 * ux * uy * uy))
    d = (r - radius) * 0.8  # first-order: the perturbations stretch distances
    return _rounded_intersection(d, -p[..., 2], 0.004)


def _box(p: np.ndarray, lo: tuple[float, float, float], hi: tuple[float, float, float],
         radius: float = 0.0) -> np.ndarray:
    """Rounded box given by its corners (``radius``: edge rounding, <= half the thinnest side)."""
    c = tuple(0.5 * (a + b) for a, b in zip(lo, hi, strict=True))
    h = tuple(0.5 * (b - a) for a, b in zip(lo, hi, strict=True))
    return _round_box(p, c, h, radius)


def _cylinder(p: np.ndarray, axis: int, centre: tuple[float, float, float], radius: float,
              half_length: float) -> np.ndarray:
    """Exact SDF of a capped cylinder along coordinate ``axis``."""
    q = p - np.asarray(centre, dtype=p.dtype)
    other = [i for i in range(3) if i != axis]
    dr = np.hypot(q[..., other[0]], q[..., other[1]]) - radius
    dz = np.abs(q[..., axis]) - half_length
    return (np.hypot(np.maximum(dr, 0.0), np.maximum(dz, 0.0))
            + np.minimum(np.maximum(dr, dz), 0.0))


def sdf_bracket(p: np.ndarray) -> np.ndarray:
    """SDF of ``bracket`` at points ``(..., 3)`` (metres); negative inside.

    An L bracket of 6 mm plate: a 90 x 60 mm foot on the table and a 50 mm upright along
    its ``-y`` edge, a 5 mm wide, 2.5 mm deep groove across the foot's top face, two
    10 mm through-holes in the foot and one 12 mm through-hole in the upright; edges
    rounded by 1 mm, so its faces are flat and its edges sharp at the scanner's scale.
    """
    t = 0.006
    foot = _box(p, (-0.045, -0.030, 0.0), (0.045, 0.030, t), 0.001)
    upright = _box(p, (-0.045, -0.030, 0.0), (0.045, -0.030 + t, 0.050), 0.001)
    d = np.minimum(foot, upright)
    k = 0.0008
    groove = _box(p, (-0.050, 0.0035, t - 0.0025), (0.050, 0.0085, t + 0.010))
    d = _smax(d, -groove, k)
    for x in (-0.025, 0.025):
        d = _smax(d, -_cylinder(p, 2, (x, 0.016, t / 2), 0.005, 0.02), k)
    d = _smax(d, -_cylinder(p, 1, (0.0, -0.027, 0.032), 0.006, 0.02), k)
    return d


_CUP_R, _CUP_H, _CUP_WALL, _CUP_FLOOR = 0.035, 0.085, 0.0025, 0.005
_CUP_DX = -0.011  # shifts the cup so that cup + handle is centred on the z axis


def sdf_cup(p: np.ndarray) -> np.ndarray:
    """SDF of ``cup`` at points ``(..., 3)`` (metres); negative inside.

    A 70 mm wide, 85 mm tall cup with a 2.5 mm wall, a 5 mm floor, a rim rounded to a
    half circle, an open top (a 77 mm deep concavity), and a loop handle (a 3.5 mm
    tube on a 13 mm radius, in the ``x z`` plane on the ``+x`` side).
    """
    q = p - np.array([_CUP_DX, 0.0, 0.0], dtype=p.dtype)
    rho = np.hypot(q[..., 0], q[..., 1])
    z = q[..., 2]
    rm = _CUP_R - _CUP_WALL / 2
    # the wall: a 2D capsule in (rho, z) from (rm, floor) to (rm, H), radius wall / 2
    wz = z - np.clip(z, _CUP_FLOOR, _CUP_H - _CUP_WALL / 2)
    wall = np.hypot(rho - rm, wz) - _CUP_WALL / 2
    # the floor: a disc rho <= R, 0 <= z <= floor, outer bottom edge rounded by 1 mm
    floor = _cylinder(q, 2, (0.0, 0.0, _CUP_FLOOR / 2), _CUP_R - 0.001,
                      _CUP_FLOOR / 2 - 0.001) - 0.001
    d = np.minimum(wall, floor)
    # the handle: a torus in the x z plane, kept outside the cup's body
    c = np.array([_CUP_R + 0.006, 0.0, 0.045], dtype=p.dtype)
    h = q - c
    ring = np.hypot(np.hypot(h[..., 0], h[..., 2]) - 0.013, h[..., 1]) - 0.0035
    handle = np.maximum(ring, (_CUP_R - 0.0008) - rho)
    return np.minimum(d, handle)


def _bump_directions() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(20261201)
    n = 28
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) * 0.8  # the bumps on the upper part, which the laser sees
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    amp = rng.uniform(0.0015, 0.0035, n) * rng.choice([-1.0, 1.0], n, p=[0.3, 0.7])
    width = rng.uniform(0.12, 0.22, n)  # radians
    return d, amp, width


_BUMPS = _bump_directions()


def sdf_bumpy_blob(p: np.ndarray) -> np.ndarray:
    """SDF (first order) of ``bumpy_blob`` at points ``(..., 3)`` (metres).

    ``blob``'s potato (low-order harmonics, 42 mm mean radius) with 28 Gaussian bumps and
    dents, 1.5-3.5 mm high and 5-9 mm wide (fixed seed), flattened where it rests.
    """
    c = np.array([0.0, 0.0, 0.036], dtype=p.dtype)
    q = p - c
    r = np.linalg.norm(q, axis=-1)
    u = q / np.maximum(r, 1e-9)[..., None]
    ux, uy, uz = u[..., 0], u[..., 1], u[..., 2]
    radius = 0.042 * (1.0 + 0.12 * ux * uy + 0.10 * (uz * uz - 0.33) + 0.06 * ux
                      - 0.05 * uy * uz)
    d_, amp, width = (x.astype(p.dtype) for x in _BUMPS)
    ang2 = 2.0 * (1.0 - u @ d_.T)  # (..., n): squared chord ~ squared angle
    radius = radius + np.exp(ang2 * (-0.5 / width**2)) @ amp
    d = (r - radius) * 0.7  # first-order: the bumps' slopes stretch distances
    return _rounded_intersection(d, -p[..., 2], 0.004)


def sdf_near_symmetric(p: np.ndarray) -> np.ndarray:
    """SDF (first order) of ``near_symmetric`` at points ``(..., 3)`` (metres).

    A 100 mm bottle, nearly a surface of revolution: its cross-sections are ellipses 2 %
    wider in ``x`` than in ``y`` and its body tapers by 2 mm, with one small feature (a
    6 mm wide round boss at mid-height on the ``+y`` side, 0.7 mm proud of the tapered body).
    """
    from scipy.interpolate import PchipInterpolator

    zs = np.array([0.0, 0.055, 0.072, 0.085, 0.1])
    rs = np.array([0.032, 0.030, 0.020, 0.013, 0.013])
    profile = PchipInterpolator(zs, rs, extrapolate=True)
    dprofile = profile.derivative()
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    zc = np.clip(z, 0.0, 0.1)
    rho = np.hypot(x / 1.02, y)
    slope = dprofile(zc)
    side = (rho - profile(zc)) / np.sqrt(1.0 + slope * slope)
    slab = np.maximum(-z, z - 0.1)
    d = _rounded_intersection(side, slab, 0.002)
    boss = _sphere(p, (0.0, 0.0305 - 0.0015, 0.035), 0.003)
    return np.minimum(d, boss)


def sdf_thin_wall(p: np.ndarray) -> np.ndarray:
    """SDF of ``thin_wall`` at points ``(..., 3)`` (metres); negative inside.

    A 1.8 mm fin, 70 mm long and 60 mm tall with a rounded top, standing on a 80 x 40 x
    8 mm base along ``x``, stiffened by one 1.5 mm gusset across it.
    """
    base = _box(p, (-0.040, -0.020, 0.0), (0.040, 0.020, 0.008), 0.001)
    fin = _box(p, (-0.035, -0.0009, 0.0), (0.035, 0.0009, 0.060), 0.0006)
    # the fin's top is an arc: cut by a big sphere (radius 80 mm, crest at z = 60 mm)
    fin = np.maximum(fin, _sphere(p, (0.0, 0.0, 0.060 - 0.080), 0.080))
    gusset = _box(p, (0.012, -0.016, 0.0), (0.0135, 0.016, 0.030), 0.0005)
    # the gusset's outer edges slope: keep it under the plane z = 30 mm - |y| * 1.4
    gusset = np.maximum(gusset, (p[..., 2] - 0.030 + 1.4 * np.abs(p[..., 1])) / np.sqrt(2.96))
    return np.minimum(np.minimum(base, fin), gusset)


@dataclass(frozen=True)
class _Spec:
    sdf: Sdf | None
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    #: the decimation's planar quadrics (False for the issue-11 objects: on their 1 mm
    #: rounded edges and thin walls they fold triangles through each other)
    planar: bool = True


#: Names of the objects the simulator can build, with their SDF and a bounding box.
OBJECTS: dict[str, _Spec] = {
    "dimple_block": _Spec(sdf_dimple_block, (-0.053, -0.043, -0.003), (0.053, 0.043, 0.063)),
    "vase": _Spec(sdf_vase, (-0.054, -0.054, -0.003), (0.054, 0.054, 0.113)),
    "blob": _Spec(sdf_blob, (-0.065, -0.065, -0.003), (0.065, 0.065, 0.095)),
    "sphere": _Spec(None, (-0.04, -0.04, 0.0), (0.04, 0.04, 0.08)),
    # issue 11: geometries the back half must hold on (thin walls, through-holes, a deep
    # concavity, flat faces, a near-symmetric body)
    "bracket": _Spec(sdf_bracket, (-0.046, -0.031, -0.003), (0.046, 0.031, 0.053), False),
    "cup": _Spec(sdf_cup, (-0.047, -0.037, -0.003), (0.048, 0.037, 0.088), False),
    "bumpy_blob": _Spec(sdf_bumpy_blob, (-0.044, -0.045, -0.003), (0.048, 0.045, 0.087),
                        False),
    "near_symmetric": _Spec(sdf_near_symmetric, (-0.036, -0.036, -0.003),
                            (0.036, 0.036, 0.103), False),
    "thin_wall": _Spec(sdf_thin_wall, (-0.041, -0.021, -0.003), (0.041, 0.021, 0.063), False),
}


# --------------------------------------------------------------------------- meshing
def mesh_sdf(sdf: Sdf, lo: np.ndarray, hi: np.ndarray, voxel: float) -> TriangleMesh:
    """Mesh the zero level set of an SDF with marching cubes.

    Parameters
    ----------
    sdf : callable
        ``sdf(points (..., 3) float32, metres) -> (...) float`` negative inside.
    lo, hi : (3,) float64, metres
        A box that contains the object; the grid gets one extra voxel of margin.
    voxel : float, metres
        Grid spacing.

    Returns
    -------
    TriangleMesh
        Outward-oriented faces.

    References
    ----------
    Lewiner et al. (2003), via ``skimage.measure.marching_cubes``.
    """
    from skimage.measure import marching_cubes

    if voxel <= 0:
        raise ValueError(f"voxel must be > 0 metres, got {voxel}")
    # an odd offset keeps grid planes off the flat faces of the objects (z = 0 etc.)
    lo = np.asarray(lo, dtype=np.float64) - 1.537 * voxel
    hi = np.asarray(hi, dtype=np.float64) + voxel
    n = np.ceil((hi - lo) / voxel).astype(int) + 1
    axes = [(lo[i] + voxel * np.arange(n[i])).astype(np.float32) for i in range(3)]
    vol = np.zeros(tuple(n), dtype=np.float32)
    gy, gz = np.meshgrid(axes[1], axes[2], indexing="ij")
    for i, x in enumerate(axes[0]):  # one slab of the grid at a time (memory)
        pts = np.stack([np.full_like(gy, x), gy, gz], axis=-1)
        vol[i] = sdf(pts)
    verts, faces, _, _ = marching_cubes(vol, 0.0, spacing=(voxel,) * 3, allow_degenerate=False)
    mesh = TriangleMesh(verts.astype(np.float64) + lo, faces.astype(np.int64))
    if mesh.volume() < 0:
        mesh = TriangleMesh(mesh.vertices, mesh.faces[:, ::-1].copy())
    return mesh


def decimate_mesh(mesh: TriangleMesh, faces: int, planar: bool = True) -> TriangleMesh:
    """Quadric edge-collapse decimation to about ``faces`` triangles.

    Parameters
    ----------
    mesh : TriangleMesh
    faces : int
        Target number of triangles (the input is returned if it has fewer).
    planar : bool
        pymeshlab's ``planarquadric`` (extra quadrics that keep planar regions planar).
        On small rounded edges (1 mm at a 0.6 mm grid) and 2 mm walls it lets collapses
        fold triangles through each other (self-intersections); the issue-11 objects
        are decimated without it.

    Returns
    -------
    TriangleMesh
        Unreferenced vertices removed; orientation kept.

    References
    ----------
    Garland, M., Heckbert, P. S. (1997), via pymeshlab's
    ``meshing_decimation_quadric_edge_collapse``.
    """
    import pymeshlab

    if faces < 4:
        raise ValueError(f"faces must be >= 4, got {faces}")
    if len(mesh.faces) <= faces:
        return mesh
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.vertices,
                               face_matrix=mesh.faces.astype(np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(faces), qualitythr=0.5,
                                                preservenormal=True, preservetopology=True,
                                                optimalplacement=True, planarquadric=planar,
                                                autoclean=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return TriangleMesh(np.asarray(m.vertex_matrix(), dtype=np.float64),
                        np.asarray(m.face_matrix(), dtype=np.int64))


def icosphere(radius: float, centre: np.ndarray, subdivisions: int = 5) -> TriangleMesh:
    """A sphere as a subdivided icosahedron with every vertex on the sphere.

    Parameters
    ----------
    radius : float, metres
    centre : (3,) float64, metres
    subdivisions : int
        ``20 * 4**subdivisions`` triangles.
    """
    import open3d as o3d

    ico = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    ico = ico.subdivide_midpoint(int(subdivisions))
    v = np.asarray(ico.vertices, dtype=np.float64)
    v = v / np.linalg.norm(v, axis=1, keepdims=True) * radius + np.asarray(centre)
    mesh = TriangleMesh(v, np.asarray(ico.triangles, dtype=np.int64))
    if mesh.volume() < 0:
        mesh = TriangleMesh(mesh.vertices, mesh.faces[:, ::-1].copy())
    return mesh


def _to_float32_grid(mesh: TriangleMesh) -> TriangleMesh:
    return TriangleMesh(mesh.vertices.astype(np.float32).astype(np.float64), mesh.faces)


def make_object(name: str, *, voxel: float = 0.0006, faces: int = 40_000) -> TriangleMesh:
    """Build a ground-truth object mesh by name.

    Parameters
    ----------
    name : str
        One of :data:`OBJECTS` (``dimple_block``, ``vase``, ``blob``, ``sphere``,
        ``bracket``, ``cup``, ``bumpy_blob``, ``near_symmetric``, ``thin_wall``).
    voxel : float, metres
        Marching-cubes grid spacing (SDF objects).
    faces : int
        Target triangle count after decimation (SDF objects).

    Returns
    -------
    TriangleMesh
        In ``base`` (metres), lowest vertex at ``z = 0``, vertices float32-exact.
    """
    if name not in OBJECTS:
        raise ValueError(f"unknown object {name!r}; expected one of {', '.join(OBJECTS)}")
    spec = OBJECTS[name]
    if spec.sdf is None:
        mesh = icosphere(0.04, np.array([0.0, 0.0, 0.04]), 5)
    else:
        raw = mesh_sdf(spec.sdf, np.array(spec.lo), np.array(spec.hi), voxel)
        _log.debug("%s: marching cubes gave %d faces", name, len(raw.faces))
        mesh = decimate_mesh(raw, faces, planar=spec.planar)
        v = mesh.vertices.copy()
        v[:, 2] -= v[:, 2].min()
        mesh = TriangleMesh(v, mesh.faces)
    return _to_float32_grid(mesh)


def mesh_to_ply_bytes(mesh: TriangleMesh) -> bytes:
    """A binary little-endian PLY of the mesh (float32 vertices, int32 faces).

    Parameters
    ----------
    mesh : TriangleMesh

    Returns
    -------
    bytes
        Deterministic: the same mesh gives the same bytes.
    """
    v = np.ascontiguousarray(mesh.vertices, dtype="<f4")
    f = np.zeros(len(mesh.faces), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    f["n"] = 3
    f["idx"] = mesh.faces
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment robo3d ground truth, base frame, metres\n"
        f"element vertex {len(v)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(f)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    return header.encode("ascii") + v.tobytes() + f.tobytes()
