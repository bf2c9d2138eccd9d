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


@dataclass(frozen=True)
class _Spec:
    sdf: Sdf | None
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]


#: Names of the objects the simulator can build, with their SDF and a bounding box.
OBJECTS: dict[str, _Spec] = {
    "dimple_block": _Spec(sdf_dimple_block, (-0.053, -0.043, -0.003), (0.053, 0.043, 0.063)),
    "vase": _Spec(sdf_vase, (-0.054, -0.054, -0.003), (0.054, 0.054, 0.113)),
    "blob": _Spec(sdf_blob, (-0.065, -0.065, -0.003), (0.065, 0.065, 0.095)),
    "sphere": _Spec(None, (-0.04, -0.04, 0.0), (0.04, 0.04, 0.08)),
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


def decimate_mesh(mesh: TriangleMesh, faces: int) -> TriangleMesh:
    """Quadric edge-collapse decimation to about ``faces`` triangles.

    Parameters
    ----------
    mesh : TriangleMesh
    faces : int
        Target number of triangles (the input is returned if it has fewer).

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
                                                optimalplacement=True, planarquadric=True,
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
        One of :data:`OBJECTS` (``dimple_block``, ``vase``, ``blob``, ``sphere``).
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
        mesh = decimate_mesh(raw, faces)
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
