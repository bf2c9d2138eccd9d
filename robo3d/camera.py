"""The pinhole camera with plumb_bob (Brown–Conrady) distortion.

:class:`CameraModel` holds one camera's intrinsics (``K``, ``D``, image size, optical
frame) and projects, distorts, undistorts and casts rays; :func:`project_points` and
:func:`pixel_rays` do the same from and to the ``base`` frame at a camera pose.

Choices:

* Camera frames are optical: +x right, +y down, +z forward. Pixel ``(u, v)`` is
  (column, row) with the origin at the centre of the top-left pixel, as OpenCV and ROS
  use. A point is in front of the camera when ``z > 1e-12`` m.
* The lens model is ROS's ``plumb_bob`` (``k1 k2 p1 p2 k3``). A ``rational_polynomial``
  calibration (``k1 k2 p1 p2 k3 k4 k5 k6``, radial ``(1 + k1 r^2 + k2 r^4 + k3 r^6) /
  (1 + k4 r^2 + k5 r^4 + k6 r^6)``) whose ``k4..k6`` are zero is plumb_bob; with any of
  them non-zero, and an ``equidistant`` (fisheye) one, its images are rectified to a
  pinhole camera as they are decoded (:class:`Rectifier`, what ROS's ``image_proc``
  does), and every stage sees that pinhole camera.
* Undistortion is OpenCV's fixed-point iteration (``undistortPoints``), vectorised;
  OpenCV is the independent oracle of the tests.
* Beyond the radius where the radial term stops being monotonic
  (:func:`distortion_limit_r2`) the model folds back onto pixels inside the image: the
  carvers and the regions of interest count such points as outside the image.

References
----------
D. C. Brown, "Decentering distortion of lenses", Photogrammetric Engineering 32(3),
1966. Z. Zhang, "A flexible new technique for camera calibration", IEEE PAMI 22(11),
2000 (OpenCV's model).
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import numpy as np

from .errors import CalibrationError
from .transforms import invert_transform

__all__ = ["CameraModel", "Rectifier", "project_points", "pixel_rays", "distortion_limit_r2"]


@dataclass(frozen=True)
class CameraModel:
    """Intrinsics of one camera.

    Parameters
    ----------
    frame_id : str
        The camera's optical frame, matched against images' ``frame_id``.
    width, height : int
        Image size in pixels.
    K : (3, 3) float64
        Camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels.
    D : (5,) float64
        plumb_bob coefficients ``k1 k2 p1 p2 k3``; zeros (or empty) for none.
    """

    frame_id: str
    width: int
    height: int
    K: np.ndarray
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))

    def __post_init__(self) -> None:
        k = np.asarray(self.K, dtype=np.float64).reshape(3, 3)
        d = np.asarray(self.D, dtype=np.float64).reshape(-1)
        if d.size == 0:
            d = np.zeros(5)
        if d.size not in (4, 5, 8):
            raise CalibrationError(f"camera {self.frame_id!r}: plumb_bob D must have 5 "
                                   f"coefficients, got {d.size}")
        if d.size == 4:
            d = np.concatenate([d, [0.0]])
        if d.size == 8:  # rational_polynomial: only its plumb_bob part is modelled here
            if np.any(d[5:] != 0):
                raise CalibrationError(f"camera {self.frame_id!r}: rational_polynomial "
                                       f"k4..k6 = {d[5:].tolist()} are not a plumb_bob "
                                       f"model (the recording reader rectifies such a "
                                       f"camera's images: robo3d.camera.Rectifier)")
            d = d[:5]
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
            raise CalibrationError(f"camera {self.frame_id!r}: K or D is not finite")
        if k[0, 0] <= 0 or k[1, 1] <= 0:
            raise CalibrationError(f"camera {self.frame_id!r}: focal lengths must be "
                                   f"positive, got fx={k[0, 0]}, fy={k[1, 1]}")
        if self.width <= 0 or self.height <= 0:
            raise CalibrationError(f"camera {self.frame_id!r}: image size must be positive, "
                                   f"got {self.width}x{self.height}")
        object.__setattr__(self, "K", k)
        object.__setattr__(self, "D", d)

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        return float(self.K[1, 2])

    @property
    def has_distortion(self) -> bool:
        return bool(np.any(self.D != 0))

    # ------------------------------------------------------------------ distortion
    def distort_normalized(self, xy: np.ndarray) -> np.ndarray:
        """Apply plumb_bob distortion to normalised image coordinates ``(N, 2)``."""
        xy = np.asarray(xy, dtype=np.float64)
        if not self.has_distortion:
            return xy.copy()
        k1, k2, p1, p2, k3 = self.D[:5]
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return np.stack([xd, yd], axis=-1)

    def undistort_normalized(self, xy_d: np.ndarray, iterations: int = 20) -> np.ndarray:
        """Invert the distortion for normalised coordinates ``(N, 2)``.

        Fixed-point iteration (as OpenCV's ``undistortPoints``), vectorised; converges to
        well below 1e-9 for the distortion of ordinary lenses inside the image.
        """
        xy_d = np.asarray(xy_d, dtype=np.float64)
        if not self.has_distortion:
            return xy_d.copy()
        k1, k2, p1, p2, k3 = self.D[:5]
        x, y = xy_d[..., 0].copy(), xy_d[..., 1].copy()
        x0, y0 = xy_d[..., 0], xy_d[..., 1]
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (x0 - dx) / radial
            y = (y0 - dy) / radial
        return np.stack([x, y], axis=-1)

    # ------------------------------------------------------------------ pixels
    def normalized_to_pixels(self, xy: np.ndarray) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        u = self.fx * xy[..., 0] + self.K[0, 1] * xy[..., 1] + self.cx
        v = self.fy * xy[..., 1] + self.cy
        return np.stack([u, v], axis=-1)

    def pixels_to_normalized(self, uv: np.ndarray) -> np.ndarray:
        uv = np.asarray(uv, dtype=np.float64)
        y = (uv[..., 1] - self.cy) / self.fy
        x = (uv[..., 0] - self.cx - self.K[0, 1] * y) / self.fx
        return np.stack([x, y], axis=-1)

    def project(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project camera-frame points ``(N, 3)`` to distorted pixels.

        Returns
        -------
        pixels_uv : (N, 2) float64
        in_front : (N,) bool
            ``z > 0``; pixels of points behind the camera are meaningless.
        """
        p = np.asarray(points_cam, dtype=np.float64)
        z = p[..., 2]
        in_front = z > 1e-12
        zs = np.where(in_front, z, 1.0)
        xy = p[..., :2] / zs[..., None]
        return self.normalized_to_pixels(self.distort_normalized(xy)), in_front

    def rays(self, pixels_uv: np.ndarray) -> np.ndarray:
        """Unit ray directions ``(N, 3)`` in the camera frame through distorted pixels."""
        xy = self.undistort_normalized(self.pixels_to_normalized(pixels_uv))
        d = np.concatenate([xy, np.ones(xy.shape[:-1] + (1,))], axis=-1)
        return d / np.linalg.norm(d, axis=-1, keepdims=True)

    def pixel_footprint(self, depth: np.ndarray | float) -> np.ndarray:
        """Size of one pixel on a fronto-parallel surface at ``depth`` metres (seed eq. 8,
        ``a = delta * w / f`` with the pixel pitch ``delta`` and ``f`` in the same unit,
        i.e. ``w / f_pixels``)."""
        return np.asarray(depth, dtype=np.float64) / np.sqrt(self.fx * self.fy)


def project_points(points_base: np.ndarray, camera: CameraModel,
                   T_base_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project base-frame points ``(N, 3)`` into a camera at pose ``T_base_camera``.

    Returns ``(pixels_uv (N, 2), in_front (N,) bool)``.
    """
    t_cam_base = invert_transform(T_base_camera)
    p = np.asarray(points_base, dtype=np.float64) @ t_cam_base[:3, :3].T + t_cam_base[:3, 3]
    return camera.project(p)


def pixel_rays(pixels_uv: np.ndarray, camera: CameraModel,
               T_base_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rays through pixels in the base frame: origin ``(3,)`` and unit directions ``(N, 3)``."""
    d = camera.rays(pixels_uv) @ np.asarray(T_base_camera)[:3, :3].T
    return np.asarray(T_base_camera)[:3, 3].copy(), d


def distortion_limit_r2(camera: CameraModel) -> float:
    """Largest squared normalised radius up to which the radial distortion is monotonic.

    ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` folds back where its derivative
    ``1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3`` (``s = r^2``) first reaches zero: points further
    off-axis project to bogus pixels, possibly inside the image (the carvers and the
    region of interest treat them as outside it). ``inf`` without such a root.
    (Tangential terms are small and ignored here.)
    """
    k1, k2, _p1, _p2, k3 = camera.D[:5]
    coeffs = np.array([7.0 * k3, 5.0 * k2, 3.0 * k1, 1.0])
    nz = np.flatnonzero(coeffs)
    coeffs = coeffs[nz[0]:]
    if coeffs.size <= 1:
        return float("inf")
    roots = np.roots(coeffs)
    real = roots[(np.abs(roots.imag) < 1e-12) & (roots.real > 0)].real
    return float(real.min()) if real.size else float("inf")


#: OpenCV's iteration inverting a lens model to convergence (its default, 5 steps, leaves
#: 3.6 px at the corners of a strong rational_polynomial lens; 20 steps 5e-4 px, 50 1e-11)
_UNDISTORT_CRITERIA = (3, 100, 1e-12)  # cv2.TERM_CRITERIA_COUNT | EPS, steps, epsilon


class Rectifier:
    """Raw images of a lens model beyond plumb_bob resampled to a pinhole camera.

    ROS's ``rational_polynomial`` (8 coefficients ``k1 k2 p1 p2 k3 k4 k5 k6``) and
    ``equidistant`` (the fisheye model, 4 coefficients ``k1 k2 k3 k4``, OpenCV's
    ``cv2.fisheye``). The images are remapped once per image as they are decoded (OpenCV's
    ``initUndistortRectifyMap`` and ``remap``, bilinear, the border replicated: ROS's
    ``image_proc`` does the same), and the pipeline sees :attr:`camera`, a pinhole camera
    without distortion of the same size whose ``K`` is OpenCV's
    ``getOptimalNewCameraMatrix`` with ``alpha = 0`` (fisheye:
    ``estimateNewCameraMatrixForUndistortRectify`` with ``balance = 0``): every pixel of
    the rectified image has a source pixel in the raw one (no invented border, which the
    carve would read as background), at the cost of the raw image's outer rim
    (:attr:`kept_fraction`).

    Parameters
    ----------
    frame_id : str
    width, height : int
        The raw (and rectified) image size.
    K : (3, 3) float64
        The raw camera matrix.
    D : (8,), (12,), (14,) or (4,) float64
        The model's coefficients (:attr:`MODELS`).
    model : {"rational_polynomial", "equidistant"}
    """

    #: each model's coefficient counts and names: rational_polynomial as ROS has it (8),
    #: or with OpenCV's thin-prism (12) and tilt (14) terms, which some drivers publish
    MODELS = {"rational_polynomial": ((8, 12, 14), "k1 k2 p1 p2 k3 k4 k5 k6 [s1 s2 s3 s4 "
                                                   "[tau_x tau_y]]"),
              "equidistant": ((4,), "k1 k2 k3 k4")}

    def __init__(self, frame_id: str, width: int, height: int, K: np.ndarray,
                 D: np.ndarray, model: str = "rational_polynomial") -> None:
        import cv2

        if model not in self.MODELS:
            raise CalibrationError(f"camera {frame_id!r}: no rectification for lens model "
                                   f"{model!r} ({', '.join(self.MODELS)})")
        n, names = self.MODELS[model]
        k = np.asarray(K, dtype=np.float64).reshape(3, 3)
        d = np.asarray(D, dtype=np.float64).reshape(-1)
        if d.size not in n:
            raise CalibrationError(f"camera {frame_id!r}: {model} needs "
                                   f"{' or '.join(str(x) for x in n)} coefficients ({names}), "
                                   f"got {d.size}")
        if not (np.all(np.isfinite(k)) and np.all(np.isfinite(d))):
            raise CalibrationError(f"camera {frame_id!r}: K or D is not finite")
        self.frame_id, self.width, self.height = frame_id, int(width), int(height)
        self.K_raw, self.D_raw, self.model = k, d, model
        self.fisheye = model == "equidistant"
        size = (self.width, self.height)
        try:
            if self.fisheye:
                k_new = cv2.fisheye.estimateNewCameraMatrixForUndistortRectify(
                    k, d, size, np.eye(3), balance=0.0, new_size=size)
            else:
                k_new, _ = cv2.getOptimalNewCameraMatrix(k, d, size, 0.0, size)
        except cv2.error as exc:
            raise CalibrationError(f"camera {frame_id!r}: the {model} lens model "
                                   f"(D={d.tolist()}) has no rectified camera: {exc}") from None
        k_new = np.asarray(k_new, dtype=np.float64)
        # a lens that sees beyond what a pinhole camera can show (a fisheye of 180 degrees
        # and more) gets a focal length near 0 from OpenCV: refused, not shrunk to a dot
        if not (np.all(np.isfinite(k_new)) and k_new[0, 0] > 0.2 * k[0, 0]
                and k_new[1, 1] > 0.2 * k[1, 1]):
            raise CalibrationError(f"camera {frame_id!r}: the {model} lens model "
                                   f"(D={d.tolist()}) has no usable pinhole camera to "
                                   f"rectify to (K' = {np.round(k_new, 3).tolist()}: its "
                                   "field of view is too wide for one)")
        k_new[0, 1] = 0.0
        self.camera = CameraModel(frame_id, self.width, self.height, k_new, np.zeros(5))
        self._maps: tuple[np.ndarray, np.ndarray] | None = None
        self._raw_index: np.ndarray | None = None
        self._kept: float | None = None
        self._lock = threading.Lock()

    @property
    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """The remap tables (fixed point, built once, on first use)."""
        import cv2

        with self._lock:
            if self._maps is None:
                size = (self.width, self.height)
                if self.fisheye:
                    self._maps = cv2.fisheye.initUndistortRectifyMap(
                        self.K_raw, self.D_raw, np.eye(3), self.camera.K, size, cv2.CV_16SC2)
                else:
                    self._maps = cv2.initUndistortRectifyMap(
                        self.K_raw, self.D_raw, None, self.camera.K, size, cv2.CV_16SC2)
            return self._maps

    @property
    def kept_fraction(self) -> float:
        """The share of the raw image's area that the rectified image shows (every 4th
        pixel's, computed once)."""
        if self._kept is None:
            u, v = np.meshgrid(np.arange(0.0, self.width, 4.0),
                               np.arange(0.0, self.height, 4.0))
            q = self.raw_to_rectified(np.stack([u.ravel(), v.ravel()], 1))
            inside = ((q[:, 0] >= -0.5) & (q[:, 0] < self.width - 0.5)
                      & (q[:, 1] >= -0.5) & (q[:, 1] < self.height - 0.5))
            self._kept = float(inside.mean())
        return self._kept

    def raw_to_rectified(self, uv: np.ndarray) -> np.ndarray:
        """Raw pixels ``(N, 2)`` where the rectified camera sees the same rays (exact, the
        8-coefficient model inverted by OpenCV's iteration: no resampling)."""
        import cv2

        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if not len(uv):
            return uv.copy()
        if self.fisheye:
            return cv2.fisheye.undistortPoints(uv.reshape(-1, 1, 2), self.K_raw, self.D_raw,
                                               R=np.eye(3), P=self.camera.K,
                                               criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)
        return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K_raw, self.D_raw,
                                   P=self.camera.K, criteria=_UNDISTORT_CRITERIA).reshape(-1, 2)

    @property
    def raw_index(self) -> np.ndarray:
        """(H, W) int64: for each raw pixel the flat index of the rectified pixel nearest
        to where it lands there, -1 outside the rectified image (built once, on every
        other pixel and spread to its 2 x 2 block: a region of interest is grown by
        several pixels anyway; 0.23 s at 1280 x 960 instead of 0.9)."""
        with self._lock:
            if self._raw_index is None:
                h2, w2 = (self.height + 1) // 2, (self.width + 1) // 2
                u, v = np.meshgrid(np.arange(w2, dtype=np.float64) * 2 + 0.5,
                                   np.arange(h2, dtype=np.float64) * 2 + 0.5)
                q = np.rint(self.raw_to_rectified(np.stack([u.ravel(), v.ravel()], 1)))
                ok = ((q[:, 0] >= 0) & (q[:, 0] < self.width) & (q[:, 1] >= 0)
                      & (q[:, 1] < self.height))
                idx = np.full(len(q), -1, np.int64)
                idx[ok] = q[ok, 1].astype(np.int64) * self.width + q[ok, 0].astype(np.int64)
                full = np.repeat(np.repeat(idx.reshape(h2, w2), 2, axis=0), 2, axis=1)
                self._raw_index = np.ascontiguousarray(full[:self.height, :self.width])
            return self._raw_index

    def raw_mask(self, mask: np.ndarray) -> np.ndarray:
        """A region given on the rectified image ``(H, W)`` bool, on the raw image (each raw
        pixel takes the value of the rectified pixel it lands on; False outside it)."""
        idx = self.raw_index
        flat = np.asarray(mask, dtype=bool).reshape(-1)
        return np.where(idx >= 0, flat[np.maximum(idx, 0)], False)

    def __call__(self, image: np.ndarray) -> np.ndarray:
        """The raw image ``(H, W)`` or ``(H, W, 3)`` (uint8 or uint16) rectified."""
        import cv2

        m1, m2 = self.maps
        return cv2.remap(image, m1, m2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def describe(self) -> str:
        what = (f"rational_polynomial (k4.. = {', '.join(f'{x:g}' for x in self.D_raw[5:])})"
                if not self.fisheye else
                f"equidistant (fisheye, k1..k4 = {', '.join(f'{x:g}' for x in self.D_raw)})")
        return (f"frame {self.frame_id!r}: {what} rectified to a pinhole camera, "
                f"fx {self.camera.fx:.1f}, "
                f"fy {self.camera.fy:.1f}, cx {self.camera.cx:.1f}, cy {self.camera.cy:.1f} "
                f"(raw fx {self.K_raw[0, 0]:.1f}), which shows {100 * self.kept_fraction:.1f} "
                "% of the raw image's area: views are resampled to it, stripe centres are "
                "found in the raw frames and moved to it exactly")
