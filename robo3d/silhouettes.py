"""Object silhouettes from ambient-lit views (seed §3.2).

A silhouette is the binary image whose pixel ``(u, v)`` is 1 when the optical ray through
that pixel meets the object. It is obtained by thresholding a grey image (seed §3.2):

1. **Grey conversion.** RGB → grey with the ITU-R BT.601 luma weights
   (0.299, 0.587, 0.114), as OpenCV's ``cvtColor``. Every grey value is on the 0–255
   scale the seed uses, whatever the input dtype: ``uint8`` as it is, ``uint16`` divided
   by 257 (so 65535 → 255), floating images are taken to be in [0, 1] (scikit-image's
   convention) and multiplied by 255. A threshold ``s`` is therefore always given on the
   0–255 scale.
2. **Background subtraction** (optional). With an image of the empty scene the feature is
   the absolute grey difference ``f = |I - B|`` and the object is where ``f > s``; the
   polarity no longer applies and is recorded as ``"difference"``. An absolute
   difference keeps objects that are partly brighter and partly darker than the scene.
3. **Blur.** A Gaussian of ``blur_sigma_px`` (0 for none) against sensor noise.
4. **Region of interest.** Pixels outside the ROI ``(u0, v0, u1, v1)`` are background.
   ROIs and bounding boxes are half-open pixel ranges in numpy slice order,
   ``mask[v0:v1, u0:u1]``, so a silhouette's ``bbox`` can be passed back as an ROI.
   :func:`roi_from_box` projects the workspace box into a view to make one; without a
   box, :func:`find_roi` finds one automatically: a first segmentation of the whole
   image, the bounding box of its largest component grown by a margin (the larger of
   ``margin_px`` and 10 % of the box's size), so that the threshold of the second,
   final segmentation is chosen around the object and clutter far from it is ignored.
5. **Threshold** ``f > s`` (``"brighter"``) or ``f < s`` (``"darker"``), with ``s``
   given or found by Otsu's method on the blurred values inside the ROI. Otsu splits the
   histogram in two, and an object with a lit side and a shaded side makes three modes
   (background, shade, light): Otsu then cuts between shade and light and the shaded side
   is lost, which carves real object away. So the automatic threshold looks at the
   background too. From a sample of sure background (the pixels outside the ROI, or else
   the image's outer ring) come its level ``b`` (median) and its edge ``s_bg`` (99.5th
   percentile plus six robust standard deviations). If more than 2 % of the pixels
   beyond ``s_bg`` lie between ``s_bg`` and Otsu's ``s``, they are a shade mode of the
   object, not the blurred rim of its outline, and ``s`` moves to the midpoint between
   ``b`` and that mode's median (at least ``s_bg``); then, along the outline only (a band
   a few blur widths wide next to the background), each pixel is thresholded at the
   midpoint between ``b`` and the brightest pixel near it (never below ``s_bg``): every
   part of the outline, lit or shaded, is cut at the middle of its own step, so neither
   side is grown or shrunk, while the lit/shade edge inside the object stays inside.
   Otherwise Otsu's ``s``, the unbiased midpoint of a two-level edge, stands. (Mirror
   image for a darker object.)
6. **Holes filled.** The silhouette is the object's *whole* projected region, so every
   background region that does not reach the image border (4-connected, the dual of the
   8-connected foreground) is set to foreground: dark texture inside a bright object
   does not punch holes into the visual hull. A notch that reaches the outline is not a
   hole and is not filled. The seed fills every hole; we keep as background the enclosed
   regions larger than ``max_hole_fraction`` of the silhouette's area that look like the
   background (median grey no brighter than the background's edge ``s_bg``, step 5):
   those are see-through gaps (between a temple's columns, inside a handle), and filling
   them would keep the voxels behind them for good. A large hole brighter than any
   background is object in shadow (a pocket) and is filled; dark markings are small.
7. **Specks removed.** Of the 8-connected foreground components, those smaller than
   ``min_component_px`` pixels, or smaller than ``min_component_fraction`` of the largest
   one, are dropped. The default keeps generously: a missing silhouette pixel carves a
   true part of the object away for good, while a kept speck only widens the hull.

Quality. Each :class:`Silhouette` says whether it touches the border of the analysed
region (``touches_border``: the ROI cut it) and of the image (``touches_image_border``:
the object is cut off by the frame; with ``carving.outside_image = carve`` that view
carves the object's hidden part away). The pipeline warns naming the view.

An empty result, or one that covers every pixel of the analysed region, is a
:class:`~robo3d.errors.StageError`: both mean the threshold, polarity or lighting are
wrong for this view. The caller adds the view's topic and time to the message.

Pixel ``(u, v)`` is (column, row), origin at the centre of the top-left pixel.

References
----------
N. Otsu, "A threshold selection method from gray-level histograms", IEEE Trans. SMC 9(1),
1979.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import cv2
import numpy as np

from .camera import CameraModel, project_points
from .errors import StageError
from .transforms import invert_transform

__all__ = ["Silhouette", "segment_silhouette", "roi_from_box", "find_roi", "to_grey"]

_log = logging.getLogger(__name__)

_POLARITIES = ("brighter", "darker")


@dataclass
class Silhouette:
    """One view's silhouette and what segmentation measured.

    Attributes
    ----------
    mask : (H, W) bool
        True where the pixel's ray meets the object.
    threshold : float
        The threshold ``s`` used, on the 0–255 grey (or grey-difference) scale.
    polarity : str
        ``"brighter"``, ``"darker"`` or ``"difference"`` (background subtraction).
    area_px : int
        Foreground pixels in ``mask``.
    n_components : int
        8-connected foreground components after hole filling, before speck removal.
    touches_border : bool
        The mask reaches the border of the analysed region (the ROI, or the image): the
        object may be cut off in this view.
    centroid_uv : (2,) float64, pixels
        Mean ``(u, v)`` of the foreground pixels.
    bbox : tuple of 4 int
        ``(u0, v0, u1, v1)``, half-open: ``mask[v0:v1, u0:u1]`` holds every foreground pixel.
    touches_image_border : bool
        The mask reaches the first or last row or column of the image: the object is cut
        off by the frame in this view.
    roi : tuple of 4 int or None
        The region analysed, ``(u0, v0, u1, v1)`` half-open (the whole image if None was
        given).
    """

    mask: np.ndarray
    threshold: float
    polarity: str
    area_px: int
    n_components: int
    touches_border: bool
    centroid_uv: np.ndarray
    bbox: tuple[int, int, int, int]
    touches_image_border: bool = False
    roi: tuple[int, int, int, int] | None = None

    def summary(self) -> dict:
        """JSON-ready numbers (everything but the mask)."""
        return {
            "threshold": float(self.threshold),
            "polarity": self.polarity,
            "area_px": int(self.area_px),
            "n_components": int(self.n_components),
            "touches_border": bool(self.touches_border),
            "centroid_uv": [float(c) for c in self.centroid_uv],
            "bbox": [int(b) for b in self.bbox],
            "touches_image_border": bool(self.touches_image_border),
            "roi": None if self.roi is None else [int(r) for r in self.roi],
        }


def _describe(a: np.ndarray) -> str:
    return f"{tuple(a.shape)} {a.dtype}"


def to_grey(image: np.ndarray, *, name: str = "image") -> np.ndarray:
    """Grey values on the 0–255 scale from a grey or RGB image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) or (H, W, 1) uint8, uint16 or float
        ``uint16`` is divided by 257; floating images are taken to be in [0, 1].
        Colour images are RGB (as :meth:`ImageMessage.decode` returns them).
    name : str
        What to call the array in error messages.

    Returns
    -------
    grey : (H, W) float32, 0–255

    Raises
    ------
    ValueError
        On any other dtype or shape, or non-finite floating values.
    """
    a = np.asarray(image)
    ok_shape = a.ndim == 2 or (a.ndim == 3 and a.shape[2] in (1, 3))
    if not ok_shape or a.shape[0] == 0 or a.shape[1] == 0:
        raise ValueError(f"{name} must be (H, W) grey or (H, W, 3) RGB, got {_describe(a)}")
    if a.dtype == np.uint8:
        scale = 1.0
    elif a.dtype == np.uint16:
        scale = 1.0 / 257.0
    elif a.dtype in (np.float32, np.float64):
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} has non-finite values")
        scale = 255.0
    else:
        raise ValueError(f"{name} must be uint8, uint16 or float32/float64 in [0, 1], "
                         f"got {_describe(a)}")
    f = a.astype(np.float32)
    if f.ndim == 3:
        if f.shape[2] == 3:
            f = f @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
        else:
            f = f[..., 0]
    if scale != 1.0:
        f *= np.float32(scale)
    return np.ascontiguousarray(f, dtype=np.float32)


def _check_roi(roi, width: int, height: int) -> tuple[int, int, int, int]:
    try:
        u0, v0, u1, v1 = (int(round(float(x))) for x in roi)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"roi must be (u0, v0, u1, v1) numbers, got {roi!r}") from exc
    u0, u1 = max(u0, 0), min(u1, width)
    v0, v1 = max(v0, 0), min(v1, height)
    if u1 <= u0 or v1 <= v0:
        raise ValueError(f"roi {tuple(roi)} leaves no pixel of the {width}x{height} image")
    return u0, v0, u1, v1


def _otsu(values: np.ndarray) -> float:
    """Otsu's threshold of a 1-D float sample (256 bins over its range)."""
    lo, hi = float(values.min()), float(values.max())
    if hi - lo <= 1e-6:
        raise StageError(f"silhouette: the image is uniform (grey {lo:.1f}) inside the region "
                         "analysed, so no threshold separates object and background")
    hist, edges = np.histogram(values, bins=256, range=(lo, hi))
    centres = 0.5 * (edges[:-1] + edges[1:])
    w0 = np.cumsum(hist).astype(np.float64)
    w1 = w0[-1] - w0
    m = np.cumsum(hist * centres)
    mu0 = m / np.maximum(w0, 1)
    mu1 = (m[-1] - m) / np.maximum(w1, 1)
    between = w0 * w1 * (mu0 - mu1) ** 2
    # threshold between bin i and i+1: keep "f > s" selecting bins i+1..
    i = int(np.argmax(between[:-1]))
    return float(edges[i + 1])


def _background_level(f: np.ndarray, roi: tuple[int, int, int, int], mode: str
                      ) -> tuple[float, float] | None:
    """``(b, s_bg)``: the level and the edge of the sure background, from the pixels
    outside the ROI when they are at least 2 % of the image, else from the image's outer
    ring (2 % of its size)."""
    height, width = f.shape
    u0, v0, u1, v1 = roi
    outside = np.ones((height, width), dtype=bool)
    outside[v0:v1, u0:u1] = False
    if np.count_nonzero(outside) < 0.02 * f.size:
        ring = max(2, int(round(0.02 * min(height, width))))
        outside[:] = False
        outside[:ring, :] = outside[-ring:, :] = True
        outside[:, :ring] = outside[:, -ring:] = True
    sample = f[outside]
    if sample.size < 100:
        return None
    med = float(np.median(sample))
    spread = 6.0 * max(1.4826 * float(np.median(np.abs(sample - med))), 1.0)
    if mode == "darker":
        return med, float(np.percentile(sample, 0.5)) - spread
    return med, float(np.percentile(sample, 99.5)) + spread


def _shade_aware_threshold(inside: np.ndarray, s_otsu: float, level: tuple[float, float],
                           mode: str) -> float:
    """Otsu's ``s``, or the midpoint between background and a shade mode that Otsu put on
    the background's side (see the module docstring, step 5)."""
    b, s_bg = level
    sign = 1.0 if mode == "brighter" else -1.0
    x = sign * inside
    lo, hi = sign * s_bg, sign * s_otsu
    if lo >= hi:
        return s_otsu
    beyond = x > lo
    between = beyond & (x < hi)
    n_beyond = np.count_nonzero(beyond)
    if n_beyond == 0 or np.count_nonzero(between) <= 0.02 * n_beyond:
        return s_otsu
    shade = float(np.median(x[between]))
    return sign * max(lo, 0.5 * (sign * b + shade))


def _local_midpoint(inside: np.ndarray, level: tuple[float, float], mode: str,
                    blur_sigma_px: float) -> np.ndarray:
    """Per-pixel threshold midway between the background level and the object's level next
    to the pixel (a max filter, min filter for a darker object, over a few blur widths),
    never nearer the background than its edge ``s_bg``: each part of the outline, lit or
    shaded, is cut at the middle of its own step, so no side is grown or shrunk."""
    b, s_bg = level
    r = max(2, int(np.ceil(3 * blur_sigma_px)))
    kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    img = np.ascontiguousarray(inside, dtype=np.float32)
    if mode == "darker":
        near = cv2.erode(img, kernel, borderType=cv2.BORDER_REPLICATE)
        return np.minimum(s_bg, 0.5 * (b + near))
    near = cv2.dilate(img, kernel, borderType=cv2.BORDER_REPLICATE)
    return np.maximum(s_bg, 0.5 * (b + near))


def _fill_holes(mask: np.ndarray, max_hole_fraction: float = 1.0,
                grey: np.ndarray | None = None, s_bg: float | None = None,
                mode: str = "brighter") -> np.ndarray:
    """Foreground plus every 4-connected background region not touching the border, except
    the large ones (over ``max_hole_fraction`` of the foreground's area) that look like
    background: median grey beyond the background's edge ``s_bg`` means object in shadow
    (a pocket), which is filled; at or below it, a see-through gap, which is kept. Without
    ``s_bg`` every large hole is kept."""
    import scipy.ndimage as ndi

    bg = (~mask).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bg, connectivity=4)
    if n <= 1:
        return mask.copy()
    keep = stats[:, cv2.CC_STAT_AREA] > max_hole_fraction * np.count_nonzero(mask)
    if grey is not None and s_bg is not None and np.any(keep[1:]):
        idx = np.nonzero(keep)[0]
        idx = idx[idx > 0]
        med = np.asarray(ndi.median(grey, labels, idx))
        shadowed = med > s_bg if mode == "brighter" else med < s_bg
        keep[idx[shadowed]] = False
    keep[labels[0, :]] = True
    keep[labels[-1, :]] = True
    keep[labels[:, 0]] = True
    keep[labels[:, -1]] = True
    keep[0] = True  # label 0 is the foreground itself
    outside = keep[labels] & ~mask
    return ~outside


def segment_silhouette(
    image: np.ndarray,
    *,
    polarity: str = "brighter",
    threshold: float | None = None,
    roi: tuple[int, int, int, int] | None = None,
    blur_sigma_px: float = 1.0,
    min_component_px: int = 50,
    min_component_fraction: float = 0.01,
    fill_holes: bool = True,
    max_hole_fraction: float = 1.0,
    background: np.ndarray | None = None,
) -> Silhouette:
    """Segment the object's silhouette in one view by thresholding (seed §3.2).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
        The ambient-lit view (RGB if colour).
    polarity : {"brighter", "darker"}
        The object is where the grey value is above (``f > s``) or below (``f < s``) the
        threshold. Ignored with ``background``.
    threshold : float, optional
        ``s`` on the 0–255 scale; by default Otsu's threshold inside the ROI.
    roi : (u0, v0, u1, v1) int, optional
        Half-open pixel box (``image[v0:v1, u0:u1]``) outside which everything is
        background; clipped to the image. See :func:`roi_from_box`.
    blur_sigma_px : float
        Gaussian blur (pixels) before thresholding; 0 for none.
    min_component_px : int
        Foreground components with fewer pixels are specks and are removed.
    min_component_fraction : float
        Components smaller than this fraction of the largest one are removed too.
    fill_holes : bool
        Fill the background regions enclosed by the object (the silhouette is the whole
        projected region).
    max_hole_fraction : float
        Enclosed background regions larger than this fraction of the silhouette's area are
        see-through gaps and stay background (1.0 fills every hole, as the seed does).
    background : array like ``image``, optional
        The empty scene under the same light and pose; the feature becomes
        ``|grey(image) - grey(background)|`` and the object is where it exceeds ``s``.

    Returns
    -------
    Silhouette

    Raises
    ------
    ValueError
        Bad dtype, shape, polarity, ROI or parameter.
    StageError
        Empty silhouette, or one covering the whole analysed region, or a uniform image.

    References
    ----------
    N. Otsu, IEEE Trans. SMC 9(1), 1979 (threshold selection).
    """
    if polarity not in _POLARITIES:
        raise ValueError(f"polarity must be one of {_POLARITIES}, got {polarity!r}")
    if not np.isfinite(blur_sigma_px) or blur_sigma_px < 0:
        raise ValueError(f"blur_sigma_px must be >= 0, got {blur_sigma_px}")
    if int(min_component_px) < 0:
        raise ValueError(f"min_component_px must be >= 0, got {min_component_px}")
    if not 0.0 <= float(min_component_fraction) <= 1.0:
        raise ValueError(f"min_component_fraction must be in [0, 1], "
                         f"got {min_component_fraction}")
    if not 0.0 <= float(max_hole_fraction):
        raise ValueError(f"max_hole_fraction must be >= 0, got {max_hole_fraction}")
    if threshold is not None and not np.isfinite(threshold):
        raise ValueError(f"threshold must be finite, got {threshold}")

    f = to_grey(image)
    height, width = f.shape
    mode = polarity
    if background is not None:
        b = to_grey(background, name="background")
        if b.shape != f.shape:
            raise ValueError(f"background must have the image's size {width}x{height}, "
                             f"got {b.shape[1]}x{b.shape[0]}")
        f = np.abs(f - b)
        mode = "difference"
    if blur_sigma_px > 0:
        f = cv2.GaussianBlur(f, (0, 0), sigmaX=float(blur_sigma_px),
                             borderType=cv2.BORDER_REPLICATE)

    if roi is None:
        u0, v0, u1, v1 = 0, 0, width, height
    else:
        u0, v0, u1, v1 = _check_roi(roi, width, height)
    inside = f[v0:v1, u0:u1]

    local = None
    level = None if mode == "difference" else _background_level(f, (u0, v0, u1, v1), mode)
    if threshold is None:
        s = _otsu(inside.ravel())
        if level is not None:
            s_shade = _shade_aware_threshold(inside, s, level, mode)
            if s_shade != s:
                local = _local_midpoint(inside, level, mode, blur_sigma_px)
    else:
        s = float(threshold)
    if local is not None:
        s = s_shade
    fg_roi = inside < s if mode == "darker" else inside > s
    if local is not None:  # refine the outline only: a band along the background
        r = max(2, int(np.ceil(3 * blur_sigma_px)))
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        band = fg_roi & cv2.dilate((~fg_roi).view(np.uint8), kernel).astype(bool)
        fg_roi[band] = (inside[band] < local[band]) if mode == "darker" else \
            (inside[band] > local[band])
    where = f"(threshold s={s:.2f}, polarity {mode}, roi {(u0, v0, u1, v1)})"
    n_roi = fg_roi.size
    n_fg = int(np.count_nonzero(fg_roi))
    if n_fg == 0:
        raise StageError(f"silhouette is empty: no pixel passes the threshold {where}")
    if n_fg == n_roi:
        raise StageError(f"silhouette covers every pixel of the region analysed {where}: "
                         "wrong polarity or threshold, or the object fills the view")

    mask = np.zeros((height, width), dtype=bool)
    mask[v0:v1, u0:u1] = fg_roi
    if fill_holes:
        mask = _fill_holes(mask, max_hole_fraction, f, None if level is None else level[1],
                           mode)

    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(mask.view(np.uint8),
                                                               connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(np.int64)
    n_components = int(areas.size)
    keep_min = max(int(min_component_px), int(np.ceil(min_component_fraction * areas.max())))
    keep = np.concatenate([[False], areas >= keep_min])
    if not np.any(keep):
        raise StageError(f"silhouette is empty: all {n_components} foreground components are "
                         f"smaller than {keep_min} px (largest {int(areas.max())} px) {where}")
    mask = keep[labels]
    if np.all(mask[v0:v1, u0:u1]):
        raise StageError(f"silhouette covers every pixel of the region analysed {where}: "
                         "wrong polarity or threshold, or the object fills the view")

    vs, us = np.nonzero(mask)
    area = int(us.size)
    centroid = np.array([us.mean(), vs.mean()], dtype=np.float64)
    bbox = (int(us.min()), int(vs.min()), int(us.max()) + 1, int(vs.max()) + 1)
    touches = bool(bbox[0] <= u0 or bbox[1] <= v0 or bbox[2] >= u1 or bbox[3] >= v1)
    touches_image = bool(bbox[0] == 0 or bbox[1] == 0 or bbox[2] == width
                         or bbox[3] == height)
    n_removed = n_components - int(np.count_nonzero(keep))
    _log.debug("silhouette: s=%.2f (%s), %d px, %d components (%d specks removed)%s",
               s, mode, area, n_components, n_removed, ", touches border" if touches else "")
    return Silhouette(mask=mask, threshold=s, polarity=mode, area_px=area,
                      n_components=n_components, touches_border=touches,
                      centroid_uv=centroid, bbox=bbox, touches_image_border=touches_image,
                      roi=(u0, v0, u1, v1))


def find_roi(
    image: np.ndarray,
    *,
    margin_px: int = 10,
    **segment_kwargs,
) -> tuple[int, int, int, int]:
    """The object's region in a view without a workspace box (seed §3.2, fig. 10).

    A first segmentation of the whole image (:func:`segment_silhouette` with
    ``segment_kwargs``, Otsu's threshold unless one is given) is reduced to its largest
    8-connected component, the object; its bounding box grown on every side by the
    larger of ``margin_px`` and 10 % of its size, clipped to the image, is the ROI of
    the final segmentation. Bright clutter far from the object is then outside the
    region, and the threshold is chosen from the object and its surroundings only.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    margin_px : int
        Least growth of the box, pixels, on each side.
    **segment_kwargs
        Passed to :func:`segment_silhouette` (``polarity``, ``threshold``,
        ``blur_sigma_px``, ``background``, ...); ``roi`` is not accepted.

    Returns
    -------
    roi : (u0, v0, u1, v1) int
        Half-open pixel box, ``image[v0:v1, u0:u1]``.

    Raises
    ------
    ValueError
        Bad arguments (as :func:`segment_silhouette`), or a ``roi`` among them.
    StageError
        The first segmentation finds nothing (as :func:`segment_silhouette`).
    """
    if "roi" in segment_kwargs:
        raise ValueError("find_roi segments the whole image: do not pass roi")
    if int(margin_px) < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    first = segment_silhouette(image, **segment_kwargs)
    height, width = first.mask.shape
    n, labels, stats, _ = cv2.connectedComponentsWithStats(first.mask.view(np.uint8),
                                                           connectivity=8)
    big = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    u0 = int(stats[big, cv2.CC_STAT_LEFT])
    v0 = int(stats[big, cv2.CC_STAT_TOP])
    u1 = u0 + int(stats[big, cv2.CC_STAT_WIDTH])
    v1 = v0 + int(stats[big, cv2.CC_STAT_HEIGHT])
    gu = max(int(margin_px), int(np.ceil(0.1 * (u1 - u0))))
    gv = max(int(margin_px), int(np.ceil(0.1 * (v1 - v0))))
    return max(u0 - gu, 0), max(v0 - gv, 0), min(u1 + gu, width), min(v1 + gv, height)


# ---------------------------------------------------------------------- projection helpers
def _distortion_limit_r2(camera: CameraModel) -> float:
    """Largest squared normalised radius up to which the radial distortion is monotonic.

    ``r_d = r (1 + k1 r^2 + k2 r^4 + k3 r^6)`` folds back where its derivative
    ``1 + 3 k1 s + 5 k2 s^2 + 7 k3 s^3`` (``s = r^2``) first reaches zero: points further
    off-axis project to bogus pixels, possibly inside the image. ``inf`` without such a
    root. (Tangential terms are small and ignored here.)
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


def _edge_samples(box_min: np.ndarray, box_max: np.ndarray, n: int = 9) -> np.ndarray:
    """Points along the 12 edges of an axis-aligned box, (12 n, 3)."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if np.abs(corners[a] - corners[b]).sum() == 1]
    t = np.linspace(0.0, 1.0, n)[:, None]
    unit = np.concatenate([corners[a] + t * (corners[b] - corners[a]) for a, b in edges])
    return box_min + unit * (box_max - box_min)


def _check_box(box_min: object, box_max: object) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned box's corners as finite (3,) float64 arrays, ``max > min`` on every
    axis; ``ValueError`` otherwise."""
    lo = np.asarray(box_min, dtype=np.float64).reshape(-1)
    hi = np.asarray(box_max, dtype=np.float64).reshape(-1)
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(np.isfinite(lo) & np.isfinite(hi)):
        raise ValueError(f"box_min and box_max must be finite (3,) arrays, got {lo} and {hi}")
    if np.any(hi <= lo):
        raise ValueError(f"box_max must exceed box_min on every axis, got {lo} and {hi}")
    return lo, hi


def roi_from_box(
    box_min: np.ndarray,
    box_max: np.ndarray,
    camera: CameraModel,
    T_base_camera: np.ndarray,
    margin_px: int = 10,
) -> tuple[int, int, int, int]:
    """The image region where a workspace box can appear, for :func:`segment_silhouette`.

    The box's edges (corners and points along them, so that lens distortion bending the
    edges outward is covered) are projected with distortion; their pixel bounds, widened
    by ``margin_px`` and clipped to the image, are the ROI. When part of the box lies
    behind the camera, or beyond the radius where the lens model is monotonic, its image
    is unbounded and the whole image is returned.

    Parameters
    ----------
    box_min, box_max : (3,) float64, metres, in ``base``
    camera : CameraModel
    T_base_camera : (4, 4) float64
        Camera pose in ``base``.
    margin_px : int
        Pixels added on every side.

    Returns
    -------
    roi : (u0, v0, u1, v1) int
        Half-open pixel box, ``image[v0:v1, u0:u1]``.

    Raises
    ------
    StageError
        The box is entirely behind the camera or projects entirely outside the image.
    """
    lo, hi = _check_box(box_min, box_max)
    if margin_px < 0:
        raise ValueError(f"margin_px must be >= 0, got {margin_px}")
    T = np.asarray(T_base_camera, dtype=np.float64)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise ValueError(f"T_base_camera must be a finite (4, 4) transform, got {T.shape}")
    full = (0, 0, int(camera.width), int(camera.height))
    pts = _edge_samples(lo, hi)
    uv, in_front = project_points(pts, camera, T)
    if not np.any(in_front):
        raise StageError(f"workspace box {lo}..{hi} is entirely behind camera "
                         f"{camera.frame_id!r}")
    if not np.all(in_front):
        return full
    t_cb = invert_transform(T)
    pc = pts @ t_cb[:3, :3].T + t_cb[:3, 3]
    r2 = (pc[:, 0] ** 2 + pc[:, 1] ** 2) / pc[:, 2] ** 2
    if np.any(r2 >= _distortion_limit_r2(camera)):
        return full
    u0 = int(np.floor(uv[:, 0].min() + 0.5)) - int(margin_px)
    v0 = int(np.floor(uv[:, 1].min() + 0.5)) - int(margin_px)
    u1 = int(np.floor(uv[:, 0].max() + 0.5)) + 1 + int(margin_px)
    v1 = int(np.floor(uv[:, 1].max() + 0.5)) + 1 + int(margin_px)
    u0, v0 = max(u0, 0), max(v0, 0)
    u1, v1 = min(u1, camera.width), min(v1, camera.height)
    if u1 <= u0 or v1 <= v0:
        raise StageError(f"workspace box {lo}..{hi} projects outside the "
                         f"{camera.width}x{camera.height} image of camera {camera.frame_id!r}")
    return u0, v0, u1, v1
