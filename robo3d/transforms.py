"""Rigid transforms, quaternions and a tf2-like transform tree.

Conventions (see ``recording-format.md``): a transform with parent P and child C is the
pose of C in P, ``x_P = R @ x_C + t``; we name its 4x4 matrix ``T_P_C``. Quaternions are
``(x, y, z, w)``. Times are integer nanoseconds.

The :class:`TransformBuffer` resolves a chain between any two frames of a tree, as tf2
does: moving links are interpolated at the query time (linear for translation, slerp for
rotation); static links are constant. A gap between two samples wider than
``max_gap_ns``, a time outside a link's samples, or a chain with a missing link is a
:class:`~robo3d.errors.TransformError` that says which.

References
----------
K. Shoemake, "Animating rotation with quaternion curves", SIGGRAPH 1985 (slerp).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import TransformError

__all__ = [
    "correction_at",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_normalize",
    "quat_slerp",
    "make_transform",
    "invert_transform",
    "transform_points",
    "rotation_angle_deg",
    "euler_to_matrix",
    "TransformBuffer",
]


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Normalise quaternions ``(..., 4)`` (x, y, z, w) to unit length."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    return q / n


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` from unit quaternions ``(..., 4)`` (x, y, z, w)."""
    q = quat_normalize(q)
    x, y, z, w = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    r = np.empty(q.shape[:-1] + (3, 3))
    r[..., 0, 0] = 1 - 2 * (y * y + z * z)
    r[..., 0, 1] = 2 * (x * y - z * w)
    r[..., 0, 2] = 2 * (x * z + y * w)
    r[..., 1, 0] = 2 * (x * y + z * w)
    r[..., 1, 1] = 1 - 2 * (x * x + z * z)
    r[..., 1, 2] = 2 * (y * z - x * w)
    r[..., 2, 0] = 2 * (x * z - y * w)
    r[..., 2, 1] = 2 * (y * z + x * w)
    r[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return r


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternions ``(..., 4)`` (x, y, z, w, with w >= 0) from rotations ``(..., 3, 3)``.

    Uses Shepperd's method, branch-free over the batch: the largest of the four
    candidate denominators is chosen per matrix for numerical stability.
    """
    r = np.asarray(r, dtype=np.float64)
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    cand = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(cand, axis=1)
    q = np.zeros((m.shape[0], 4))
    # case w largest
    s = np.sqrt(np.maximum(1.0 + tr, 1e-300)) * 2
    qw = np.stack([(m[:, 2, 1] - m[:, 1, 2]) / s, (m[:, 0, 2] - m[:, 2, 0]) / s,
                   (m[:, 1, 0] - m[:, 0, 1]) / s, 0.25 * s], axis=1)
    s = np.sqrt(np.maximum(1.0 + m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2], 1e-300)) * 2
    qx = np.stack([0.25 * s, (m[:, 0, 1] + m[:, 1, 0]) / s, (m[:, 0, 2] + m[:, 2, 0]) / s,
                   (m[:, 2, 1] - m[:, 1, 2]) / s], axis=1)
    s = np.sqrt(np.maximum(1.0 + m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2], 1e-300)) * 2
    qy = np.stack([(m[:, 0, 1] + m[:, 1, 0]) / s, 0.25 * s, (m[:, 1, 2] + m[:, 2, 1]) / s,
                   (m[:, 0, 2] - m[:, 2, 0]) / s], axis=1)
    s = np.sqrt(np.maximum(1.0 + m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1], 1e-300)) * 2
    qz = np.stack([(m[:, 0, 2] + m[:, 2, 0]) / s, (m[:, 1, 2] + m[:, 2, 1]) / s, 0.25 * s,
                   (m[:, 1, 0] - m[:, 0, 1]) / s], axis=1)
    allq = np.stack([qw, qx, qy, qz], axis=1)
    q = allq[np.arange(m.shape[0]), k]
    q = np.where(q[:, 3:4] < 0, -q, q)
    return quat_normalize(q).reshape(r.shape[:-2] + (4,))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Spherical linear interpolation between quaternions, vectorised.

    Parameters
    ----------
    q0, q1 : (N, 4) float64
        Unit quaternions (x, y, z, w).
    alpha : (N,) float64
        Interpolation parameter in [0, 1].
    """
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    alpha = np.asarray(alpha, dtype=np.float64)[..., None]
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    dot = np.abs(dot)
    theta = np.arccos(np.clip(dot, -1.0, 1.0))
    sin_t = np.sin(theta)
    small = sin_t < 1e-9
    safe = np.where(small, 1.0, sin_t)
    w0 = np.where(small, 1.0 - alpha, np.sin((1.0 - alpha) * theta) / safe)
    w1 = np.where(small, alpha, np.sin(alpha * theta) / safe)
    return quat_normalize(w0 * q0 + w1 * q1)


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """4x4 homogeneous transforms ``(..., 4, 4)`` from rotations ``(..., 3, 3)`` or
    quaternions ``(..., 4)`` and translations ``(..., 3)``."""
    rotation = np.asarray(rotation, dtype=np.float64)
    translation = np.asarray(translation, dtype=np.float64)
    if rotation.shape[-1] == 4 and rotation.ndim >= 1 and rotation.shape[-2:] != (3, 3):
        rotation = quat_to_matrix(rotation)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    t = np.zeros(shape + (4, 4))
    t[..., :3, :3] = rotation
    t[..., :3, 3] = translation
    t[..., 3, 3] = 1.0
    return t


def invert_transform(t: np.ndarray) -> np.ndarray:
    """Inverse of rigid transforms ``(..., 4, 4)``."""
    t = np.asarray(t, dtype=np.float64)
    r = t[..., :3, :3]
    rt = np.swapaxes(r, -1, -2)
    out = np.zeros_like(t)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def transform_points(t: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a rigid transform ``(4, 4)`` to points ``(N, 3)``; returns ``(N, 3)``."""
    t = np.asarray(t, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    return points @ t[:3, :3].T + t[:3, 3]


def rotation_angle_deg(r: np.ndarray) -> np.ndarray:
    """Angle of rotation matrices ``(..., 3, 3)`` in degrees."""
    r = np.asarray(r, dtype=np.float64)
    c = (np.trace(r, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def euler_to_matrix(axis_order: str, angles: np.ndarray) -> np.ndarray:
    """Rotation matrix for successive rotations about the *current* (intrinsic) axes.

    ``euler_to_matrix("zyx", (phi, theta, psi))`` is ``Rz(phi) @ Ry(theta) @ Rx(psi)``.
    """
    angles = np.asarray(angles, dtype=np.float64)
    r = np.eye(3)
    for ax, a in zip(axis_order, angles, strict=True):
        c, s = np.cos(a), np.sin(a)
        if ax == "x":
            m = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
        elif ax == "y":
            m = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
        elif ax == "z":
            m = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        else:
            raise ValueError(f"axis must be one of x, y, z, got {ax!r}")
        r = r @ m
    return r


@dataclass
class _Link:
    parent: str
    child: str
    static: bool
    stamps_ns: np.ndarray  # (N,) int64, sorted
    translations: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4)
    topic: str = "/tf"


@dataclass
class TransformBuffer:
    """A tree of timed transforms, queried like tf2.

    Parameters
    ----------
    max_gap_ns : int
        Widest gap between two samples of a moving link across which a pose is still
        interpolated (the config's ``max_pose_gap``).
    path : str, optional
        The recording's file, named in errors.
    """

    max_gap_ns: int = 50_000_000
    path: str | None = None
    _links: dict[str, _Link] = field(default_factory=dict)  # keyed by child frame

    # ------------------------------------------------------------------ building
    def add(
        self,
        parent: str,
        child: str,
        stamps_ns: np.ndarray,
        translations: np.ndarray,
        quats: np.ndarray,
        *,
        static: bool = False,
        topic: str = "/tf",
    ) -> None:
        """Add the samples of one link ``parent -> child``.

        Samples are sorted by time; duplicated stamps keep the last sample. A child
        with two different parents is an error (a tree has one parent per frame).
        """
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        tr = np.asarray(translations, dtype=np.float64).reshape(-1, 3)
        q = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
        if not (len(stamps) == len(tr) == len(q)):
            raise ValueError("stamps, translations and quats must have the same length")
        if child in self._links:
            old = self._links[child]
            if old.parent != parent:
                raise TransformError(
                    f"frame {child!r} has two parents, {old.parent!r} and {parent!r}",
                    path=self.path,
                    topic=topic,
                )
            stamps = np.concatenate([old.stamps_ns, stamps])
            tr = np.concatenate([old.translations, tr])
            q = np.concatenate([old.quats, q])
            static = static and old.static
        order = np.argsort(stamps, kind="stable")
        stamps, tr, q = stamps[order], tr[order], q[order]
        # keep the last of duplicated stamps
        keep = np.ones(len(stamps), dtype=bool)
        keep[:-1] = stamps[1:] != stamps[:-1]
        self._links[child] = _Link(parent, child, static, stamps[keep], tr[keep],
                                   quat_normalize(q[keep]), topic)

    def copy(self) -> TransformBuffer:
        """An independent copy of the tree (its samples copied)."""
        import copy

        return TransformBuffer(self.max_gap_ns, self.path, copy.deepcopy(self._links))

    def replace_static(self, parent: str, child: str, T_parent_child: np.ndarray, *,
                       topic: str = "/tf_static") -> None:
        """Make ``parent -> child`` the one static link ``T_parent_child`` (4, 4), dropping
        whatever samples the link had (a calibration replacing a recorded hand-eye):
        unlike :meth:`add`, the old samples are not merged."""
        self._links.pop(child, None)
        T = np.asarray(T_parent_child, dtype=np.float64)
        self.add(parent, child, np.zeros(1, np.int64), T[:3, 3], matrix_to_quat(T[:3, :3]),
                 static=True, topic=topic)

    @property
    def frames(self) -> set[str]:
        """Every frame named in the tree."""
        out = set(self._links)
        out.update(link.parent for link in self._links.values())
        return out

    def links(self) -> list[tuple[str, str, bool, int]]:
        """``(parent, child, static, n_samples)`` of every link."""
        return [(k.parent, k.child, k.static, len(k.stamps_ns)) for k in self._links.values()]

    def link_samples(self, parent: str, child: str) -> tuple[np.ndarray, np.ndarray]:
        """Raw samples of one direct link: stamps ``(N,)`` and transforms ``(N, 4, 4)``."""
        link = self._links.get(child)
        if link is None or link.parent != parent:
            raise TransformError(f"no direct link {parent} -> {child}", path=self.path)
        return link.stamps_ns.copy(), make_transform(link.quats, link.translations)

    # ------------------------------------------------------------------ queries
    def _chain_to_root(self, frame: str) -> list[str]:
        chain = [frame]
        seen = {frame}
        while chain[-1] in self._links:
            parent = self._links[chain[-1]].parent
            if parent in seen:
                raise TransformError(f"transform tree has a cycle through {parent!r}",
                                     path=self.path)
            chain.append(parent)
            seen.add(parent)
        return chain

    def _fail_at(self, bad: np.ndarray, times: np.ndarray, link: _Link, message: str) -> None:
        """Raise ``message`` as a :class:`TransformError` at the first query time where
        ``bad`` holds (nothing when it holds nowhere)."""
        if np.any(bad):
            raise TransformError(message, path=self.path, topic=link.topic,
                                 time_ns=int(times[np.argmax(bad)]))

    def _link_at(self, link: _Link, times: np.ndarray, what: str) -> np.ndarray:
        if link.static or len(link.stamps_ns) == 1:
            if not link.static and len(link.stamps_ns) == 1:
                # one sample on /tf: only usable exactly at its stamp or within the gap
                dt = np.abs(times - link.stamps_ns[0])
                self._fail_at(dt > self.max_gap_ns, times, link,
                              f"{what}: link {link.parent} -> {link.child} has a single "
                              f"sample at {link.stamps_ns[0]} ns, too far from the query")
            t = make_transform(link.quats[0], link.translations[0])
            return np.broadcast_to(t, times.shape + (4, 4)).copy()
        s = link.stamps_ns
        idx = np.searchsorted(s, times, side="right")
        self._fail_at((times < s[0]) | (times > s[-1]), times, link,
                      f"{what}: time outside the samples of {link.parent} -> {link.child} "
                      f"({s[0]} .. {s[-1]} ns)")
        i1 = np.clip(idx, 1, len(s) - 1)
        i0 = i1 - 1
        gap = s[i1] - s[i0]
        exact = times == s[i0]
        bad = (gap > self.max_gap_ns) & ~exact & (times != s[i1])
        if np.any(bad):
            k = int(np.argmax(bad))
            self._fail_at(bad, times, link,
                          f"{what}: the samples of {link.parent} -> {link.child} around this "
                          f"time are {gap[k] / 1e6:.1f} ms apart, more than max_pose_gap "
                          f"{self.max_gap_ns / 1e6:.1f} ms")
        alpha = (times - s[i0]).astype(np.float64) / np.maximum(gap, 1).astype(np.float64)
        alpha = np.clip(alpha, 0.0, 1.0)
        tr = link.translations[i0] * (1 - alpha[:, None]) + link.translations[i1] * alpha[:, None]
        q = quat_slerp(link.quats[i0], link.quats[i1], alpha)
        return make_transform(q, tr)

    def lookup(self, parent: str, child: str, times_ns: np.ndarray | int) -> np.ndarray:
        """Pose of ``child`` in ``parent`` at the given times: ``T_parent_child``.

        Parameters
        ----------
        parent, child : str
            Frame names; any two frames connected through the tree.
        times_ns : int or (M,) int64
            Query times in nanoseconds.

        Returns
        -------
        (4, 4) or (M, 4, 4) float64
        """
        scalar = np.ndim(times_ns) == 0
        times = np.atleast_1d(np.asarray(times_ns, dtype=np.int64))
        what = f"pose of {child!r} in {parent!r}"
        for f in (parent, child):
            if f not in self.frames:
                known = ", ".join(sorted(self.frames)) or "none"
                raise TransformError(f"{what}: frame {f!r} is not in the transform tree "
                                     f"(frames: {known})", path=self.path)
        up_c = self._chain_to_root(child)
        up_p = self._chain_to_root(parent)
        common = next((f for f in up_c if f in set(up_p)), None)
        if common is None:
            raise TransformError(
                f"{what}: the chain does not connect: {' -> '.join(reversed(up_c))} and "
                f"{' -> '.join(reversed(up_p))} have no common frame (missing link between "
                f"{up_c[-1]!r} and {up_p[-1]!r})", path=self.path)
        eye = np.broadcast_to(np.eye(4), times.shape + (4, 4))
        t_common_child = eye.copy()
        for f in up_c[: up_c.index(common)]:
            t_common_child = self._link_at(self._links[f], times, what) @ t_common_child
        t_common_parent = eye.copy()
        for f in up_p[: up_p.index(common)]:
            t_common_parent = self._link_at(self._links[f], times, what) @ t_common_parent
        out = invert_transform(t_common_parent) @ t_common_child
        return out[0] if scalar else out


def correction_at(origin: np.ndarray, rotation: np.ndarray, translation: np.ndarray
                  ) -> np.ndarray:
    """The rigid ``base`` transform (4, 4) that a correction applies at one frame whose
    sensor was at ``origin`` (3,): ``[R, (I - R) o + t]`` (the alignment's model,
    :mod:`robo3d.registration`; here so that the evaluation need not import it)."""
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = (np.eye(3) - rotation) @ np.asarray(origin, dtype=np.float64) + translation
    return out
