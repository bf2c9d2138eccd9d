"""Object silhouettes from ambient-lit views (seed §3.2).

A silhouette is the binary image whose pixel ``(u, v)`` is 1 when the optical ray through
that pixel meets the object. The seed thresholds a grey image with a fixed polarity
(object brighter or darker than the background); real cells break that (an orange object
on a white table is darker than the table and brighter than the markers printed on it),
so the default, ``polarity="auto"``, thresholds a colour difference instead:

A. **Background sample.** Pixels known to be background: those outside the ROI (the
   projected workspace box), taken in a frame around it a quarter of the ROI's size wide
   (the table and wall next to the object, not clutter far off), when they are at least
   2 % of the image; else (the box covers the whole view, or there is none) the image's
   outer ring, 2 % of its size wide (``Silhouette.background_sample``). With a box, the
   ROI's own pixels outside the box's projected outline (:func:`region_from_box`, the
   convex hull of its projected edges grown by the ROI's margin) join the sample and are
   never object: seen from above, a box projects to a hexagon whose corners leave the
   table right next to the object inside the ROI's rectangle, and a small turntable's
   plate before a dark room may lie there only (measured: a red cup on a turntable, its
   views' worst IoU 0.387 -> 0.948; DTU scan 24's masks unchanged).
B. **Colour modes.** The sample's CIE L*a*b* colours (after the blur of step 3) are
   clustered by k-means (6 modes, k-means++ seeding, fixed seed); each mode keeps its
   mean and covariance plus a noise floor of (2 Lab units)² — a saturated white table has
   no spread of its own. Only the sample's *flat* pixels (5 x 5 local colour contrast at
   most 3 times the sample's median, or 2 Lab units) are modelled: the blurred rim of a
   printed marker holds every grey between paper and ink, and would make any grey object
   look like the table. A ring sample may hold the object where the frame cuts it off
   (DTU): there only flat modes count as background (median local contrast below 1.7 Lab
   units for a near-neutral mode, chroma < 12, and below 0.8 for a coloured one, since
   tables, cloths and walls are flat and mostly neutral, objects textured or coloured; in
   a noisy image where none is that flat, those at most 1.5 times as rough as the
   flattest). A mode that runs around the image (along three of its sides, or in 40 % of
   the ring) is background when at most 1.6 times as rough as the limit: a table printed
   with markers, not an object cut off by the frame (:func:`_surrounds`).
C. **Feature.** ``f`` = Mahalanobis distance of each pixel's colour to the nearest mode, in
   the modes' standard deviations: brighter, darker and differently coloured objects all
   stand out, in one polarity.
D. **Threshold.** ``f`` is heavy-tailed (an object's colours lie at many distances from
   the background's), so ``s`` is Otsu's threshold of ``log(1 + f)`` inside the ROI (at
   least 2). Along the outline (a band a few blur widths wide) each pixel is cut midway
   between the background's level and the object's nearby (step 5's local midpoint), so
   a low ``s`` does not grow the silhouette by the blur. With a sample from outside the
   ROI, foreground whose colour lies within 3 Lab units of a segment between two
   background modes is background: the blurred rim of a printed marker (every grey
   between paper and ink) would otherwise close into rings and, filled, into blobs, and a
   shadow on the table is the table's colour darkened towards the ink. So is a background
   colour darkened towards black, down to ``shadow_darkest`` (0.55) of its Lab
   coordinates (a shadow on a plain table, where no ink mode lies), when most of the rest
   of the foreground is coloured unlike the background (a*b* distance 8 or more) or far
   darker than the darkest shadow (a black object): a grey or white object shades through
   those colours itself and keeps its shadow. When such pixels are most of the foreground
   the object itself has those colours (a grey object on a black-and-white table), and
   only a 2 px band along the background is dropped.
   Steps 6-7 follow, with the background's edge ``s_bg`` from the sample pixels below
   ``s``.
E. **GrabCut** (``grabcut=True``, the pipeline's default): the mask seeds OpenCV's GrabCut
   (Rother et al. 2004) at most 640 px wide (a webcam view at full resolution: at half
   resolution its outline, scaled back, is 1-2 px off all round), one iteration: the mask
   eroded by 12 px is sure object, the mask probable object, a 24 px band around it
   probable background, the rest and everything outside the ROI sure background, and so
   are the blends of two background colours that step D dropped (a shadow, a marker's
   rim: GrabCut's mixtures would give their dark greys back to a dark face beside them;
   not when the object itself has such colours and only its rims were dropped). Its
   colour mixtures and graph cut move the outline onto the object's colour edge where a
   shadow, a reflection on the table or a shaded part near a background colour misled
   the threshold. Holes and specks are cleaned again afterwards; a refinement that loses
   the object leaves the thresholded mask.
F. **Edge refinement** (``edge_refine_px``, default 3; :func:`refine_edges`): at full
   resolution, each pixel within 3 px of the outline is object when its colour, as a
   blend of the colours just inside and just outside the outline (the nearest pixels
   3 px deep on either side), is more than half the object's: the outline passes where
   the ray through the pixel's centre leaves the object (the ground truth's definition),
   on paper, ink, shadow or backdrop alike. Where the two sides look alike, or the pixel
   is no blend of them (texture), it keeps its label. What it cannot mend: an error
   wider than its reach (GrabCut taking in a black square that touches the object,
   ``tests/test_silhouettes.py`` keeps such a scene as a strict xfail).

What these steps gave on DTU scan24, Middlebury templeSparseRing and the benchmark's
simulated cells, and what they cost, is recorded in ``benchmarks/README.md`` ("Notes moved
from robo3d/silhouettes.py"); ``benchmarks/front_end.py`` measures it again.
Known limit: an object whose colours are the background's (a white object on a white
table, a grey object whose shaded side has the wall's, a shadow's or a marker blend's
grey) is not told apart by colour (``tests/test_silhouettes.py`` keeps such scenes as
strict xfails).

The seed's grey threshold (``polarity="brighter"`` / ``"darker"``):

1. **Grey conversion.** RGB → grey with the ITU-R BT.601 luma weights
   (0.299, 0.587, 0.114), as OpenCV's ``cvtColor``. Every grey value is on the 0–255
   scale the seed uses, whatever the input dtype: ``uint8`` as it is, ``uint16`` divided
   by 257 (so 65535 → 255), floating images are taken to be in [0, 1] (scikit-image's
   convention) and multiplied by 255. A threshold ``s`` is therefore always given on the
   0–255 scale.
2. **Background subtraction** (optional). With an image of the empty scene the feature is
   the absolute grey difference ``f = |I - B|`` (with ``polarity="auto"``: the colour
   difference ``ΔE = |Lab(I) - Lab(B)|``, thresholded as in D) and the object is where
   ``f > s``; the polarity is recorded as ``"difference"``. An absolute difference keeps
   objects that are partly brighter and partly darker than the scene; the colour one
   also those of the scene's grey.
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
wrong for this view. The caller adds the view's topic and time to the message; the
pipeline's stage names the view in a warning, flags it and goes on with the others
(:func:`robo3d.stages.silhouettes.stage_silhouettes`).

QA (:func:`silhouette_qa`, ``Silhouette.qa``): a mask no object in the workspace can cast
is flagged, not dropped — ``fills_region`` (over 95 % of its region), ``touches_all_sides``
(all four sides of its region, one of them inside the image: the box's own edge), and
``inverted`` (the pixels it calls object are no farther from the background's colours
than those it calls background). An object larger than the frame touching the image's
four sides is no flag (that is ``touches_image_border``), unless most views of the scan
are so and cover most of their image (``surrounds_view``, :func:`surrounding_views`: the
surroundings taken for the object). The pipeline puts the flags into
the silhouettes report per view (``views[i]["qa"]["flags"]``), lists the flagged views
(``qa_flagged_views``) and stores ``qa_flagged`` per view in ``silhouettes.npz``.

Entry points: :func:`segment_view` segments one view as the pipeline does (the ROI from
the workspace box, or :func:`find_roi`, then :func:`segment_silhouette`);
:func:`segment_silhouette` is the segmentation of one image in a given ROI. Both take
their parameters as one :class:`SegmentOptions`, made from the config's ``segmentation``
section (``SegmentOptions.from_config(cfg["segmentation"])``); its defaults are the
config's. The image, its empty scene and the ROI are per call.

Pixel ``(u, v)`` is (column, row), origin at the centre of the top-left pixel.

References
----------
N. Otsu, "A threshold selection method from gray-level histograms", IEEE Trans. SMC 9(1),
1979.
C. Rother, V. Kolmogorov, A. Blake, "GrabCut: interactive foreground extraction using
iterated graph cuts", ACM Trans. Graphics 23(3), 2004.
Y.-Y. Chuang, B. Curless, D. H. Salesin, R. Szeliski, "A Bayesian approach to digital
matting", CVPR 2001 (the two-colour blend of step F).
D. Arthur, S. Vassilvitskii, "k-means++: the advantages of careful seeding", SODA 2007.
R. Jensen, A. Dahl, G. Vogiatzis, E. Tola, H. Aanæs, "Large scale multi-view stereopsis
evaluation", CVPR 2014 (DTU, the masks scored against).
S. Seitz, B. Curless, J. Diebel, D. Scharstein, R. Szeliski, "A comparison and evaluation
of multi-view stereo reconstruction algorithms", CVPR 2006 (templeSparseRing).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from .camera import CameraModel, project_points
from .camera import distortion_limit_r2 as _distortion_limit_r2
from .errors import StageError
from .grid import check_box as _check_box
from .options import Options
from .transforms import invert_transform

__all__ = ["Silhouette", "SegmentOptions", "segment_silhouette", "segment_view", "roi_from_box",
           "region_from_box", "resegment_spurious_views", "resegment_laser_contradicted",
           "resegment_outside_box",
           "laser_pixels", "laser_outside_share", "laser_cover",
           "find_roi", "to_grey", "to_lab", "colour_difference", "refine_with_grabcut",
           "silhouette_qa", "surrounding_views", "QA_FLAGS"]

_log = logging.getLogger(__name__)

_POLARITIES = ("auto", "brighter", "darker")


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
    background_sample : str
        Where the background was sampled: ``"outside roi"`` or ``"image border"``.
    refined : bool
        The outline was refined with GrabCut.
    qa : dict
        :func:`silhouette_qa`'s verdict: ``flags`` (absurd-mask flags, empty when the
        mask is plausible) and the measurements behind them.
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
    background_sample: str = "outside roi"
    refined: bool = False
    qa: dict = field(default_factory=lambda: {"flags": []})

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
            "background_sample": self.background_sample,
            "refined": bool(self.refined),
            "qa": self.qa,
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


def _label_medians(values: np.ndarray, labels: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Median of ``values`` over each label in ``idx`` (lower median), one sort."""
    lut = np.full(int(labels.max()) + 1, -1, np.int64)
    lut[idx] = np.arange(idx.size)
    slot = lut[labels]
    sel = slot >= 0
    v, s = values[sel], slot[sel]
    order = np.lexsort((v, s))
    counts = np.bincount(s, minlength=idx.size)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    return v[order][starts + (np.maximum(counts, 1) - 1) // 2]


def _fill_holes(mask: np.ndarray, max_hole_fraction: float = 1.0,
                grey: np.ndarray | None = None, s_bg: float | None = None,
                mode: str = "brighter") -> np.ndarray:
    """Foreground plus every 4-connected background region not touching the border, except
    the large ones (over ``max_hole_fraction`` of the foreground's area) that look like
    background: median grey beyond the background's edge ``s_bg`` means object in shadow
    (a pocket), which is filled; at or below it, a see-through gap, which is kept. Without
    ``s_bg`` every large hole is kept."""
    bg = (~mask).view(np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bg, connectivity=4)
    if n <= 1:
        return mask.copy()
    keep = stats[:, cv2.CC_STAT_AREA] > max_hole_fraction * np.count_nonzero(mask)
    outer = np.zeros(n, bool)
    for edge in (labels[0, :], labels[-1, :], labels[:, 0], labels[:, -1]):
        outer[edge] = True
    if grey is not None and s_bg is not None and np.any(keep[1:] & ~outer[1:]):
        idx = np.nonzero(keep & ~outer)[0]
        idx = idx[idx > 0]
        med = _label_medians(grey, labels, idx)
        shadowed = med > s_bg if mode == "brighter" else med < s_bg
        keep[idx[shadowed]] = False
    keep[labels[0, :]] = True
    keep[labels[-1, :]] = True
    keep[labels[:, 0]] = True
    keep[labels[:, -1]] = True
    keep[0] = True  # label 0 is the foreground itself
    outside = keep[labels] & ~mask
    return ~outside


# ---------------------------------------------------------------------- colour (auto polarity)
_N_MODES = 6            # k-means modes of the background sample
_SIGMA0_LAB = 2.0       # noise floor added to every mode's covariance, Lab units
_FLAT_NEUTRAL = 1.7     # border fallback: a near-neutral mode is background if this flat
_FLAT_COLOURED = 0.8    # ... a saturated one only if this flat (Lab units, 5x5 local std)
_NEUTRAL_CHROMA = 12.0  # chroma below which a mode counts as near-neutral
_SURROUND_SIDES = 3     # border fallback: a mode along this many sides of the image ...
_SURROUND_RING = 0.4    # ... or along this share of the border ring ...
_SURROUND_ROUGH = 1.6   # ... is background when at most this many times its flat limit
_FLAT_SMOOTH_PX = 1.0   # a near-neutral mode whose roughness a Gaussian of this sigma ...
_NOISE_RATIO = 3.0      # ... cuts by this factor or more is pixel noise: flat if flat so smoothed
_MIN_THRESHOLD = 2.0    # the colour-difference threshold never goes below this (std devs)
_BLEND_LAB = 3.0        # a colour this close (Lab) to a blend of two background modes is one
_SHADOW_CHROMA = 8.0    # shadows are dropped only when the object's other colours lie this far
                        # (median, Lab a*b*) from every background mode's: a coloured object
_SHADOW_DARKER = 0.6    # ... or are darker than this times the darkest shadow: a black object


def to_lab(image: np.ndarray, *, name: str = "image") -> np.ndarray:
    """CIE L*a*b* of a grey or RGB image (OpenCV's conversion, D65 white).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) or (H, W, 1) uint8, uint16 or float in [0, 1]
        RGB if colour; a grey image is taken as R = G = B.
    name : str
        What to call the array in error messages.

    Returns
    -------
    lab : (H, W, 3) float32
        L in 0–100, a and b about -128..127.
    """
    grey = to_grey(image, name=name)  # checks dtype, shape and finiteness
    a = np.asarray(image)
    if a.ndim == 2 or a.shape[2] == 1:
        rgb = np.repeat(grey[..., None], 3, axis=2)
    elif a.dtype == np.uint8:
        rgb = a.astype(np.float32)
    elif a.dtype == np.uint16:
        rgb = a.astype(np.float32) / np.float32(257.0)
    else:
        rgb = a.astype(np.float32) * np.float32(255.0)
    rgb = np.clip(rgb, 0.0, 255.0) * np.float32(1.0 / 255.0)
    return cv2.cvtColor(np.ascontiguousarray(rgb, dtype=np.float32), cv2.COLOR_RGB2LAB)


def _sure_background(shape: tuple[int, int], roi: tuple[int, int, int, int]
                     ) -> tuple[np.ndarray, str]:
    """The sample that models the background: the pixels outside the ROI when they are at
    least 2 % of the image (``"outside roi"``), else the image's outer ring, 2 % of its
    size wide (``"image border"``). Outside the ROI only a frame around it is taken, as
    wide as a quarter of the ROI's longer side (at least 16 px), when that frame alone
    has 2 % of the image: the table and wall next to the object, not clutter far away
    whose colour may happen to be the object's."""
    height, width = shape
    u0, v0, u1, v1 = roi
    out = np.ones((height, width), dtype=bool)
    out[v0:v1, u0:u1] = False
    if np.count_nonzero(out) >= 0.02 * height * width:
        g = max(16, int(np.ceil(0.25 * max(u1 - u0, v1 - v0))))
        near = np.zeros_like(out)
        near[max(v0 - g, 0):v1 + g, max(u0 - g, 0):u1 + g] = True
        near &= out
        if np.count_nonzero(near) >= 0.02 * height * width:
            return near, "outside roi"
        return out, "outside roi"
    ring = max(2, int(round(0.02 * min(height, width))))
    out[:] = False
    out[:ring, :] = out[-ring:, :] = True
    out[:, :ring] = out[:, -ring:] = True
    return out, "image border"


_ONES_1x3 = np.ones((1, 3), np.float32)


def _local_contrast(lab: np.ndarray) -> np.ndarray:
    """Per-pixel standard deviation of the Lab colour over a 5 x 5 window (Lab units)."""
    k = (5, 5)
    lab = np.ascontiguousarray(lab, dtype=np.float32)
    mean = cv2.blur(lab, k, borderType=cv2.BORDER_REFLECT)
    sq = cv2.blur(cv2.multiply(lab, lab), k, borderType=cv2.BORDER_REFLECT)
    var = cv2.transform(cv2.subtract(sq, cv2.multiply(mean, mean)), _ONES_1x3)
    return cv2.sqrt(cv2.max(var, 0.0))


def _background_modes(lab_blurred: np.ndarray, sample: np.ndarray, kind: str,
                      lab_raw: np.ndarray | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The background's colour modes: ``(mean (3,), whitening (3, 3))`` per mode, so that
    ``|(x - mean) @ whitening|`` is the Mahalanobis distance of colour ``x`` to it.

    k-means (``_N_MODES`` modes, k-means++ seeding, fixed RNG seed) on up to 5000 sample
    pixels; each mode's covariance gets a noise floor ``_SIGMA0_LAB**2 I`` (a saturated
    white table has almost none of its own). A sample from the image border may hold an
    object cut off by the frame: there only the flat modes are background (median 5 x 5
    local contrast below ``_FLAT_NEUTRAL`` for a near-neutral mode, ``_FLAT_COLOURED``
    for a saturated one), since tables, cloths and walls are flat and mostly neutral while
    the object is textured; in a noisy image where no mode is that flat, those at most
    1.5 times as rough as the flattest (relative to their limits) are kept. A sensor's
    shot noise grows with the light, so a bright near-neutral mode can be rough with
    pixel noise alone: one whose roughness a Gaussian of ``_FLAT_SMOOTH_PX`` cuts by
    ``_NOISE_RATIO`` or more is flat when it is flat so smoothed (random scene 1163:
    white paper printed with black dots, 3.8 and 1.3 times the limit as they are, the
    paper 1.0 smoothed; texture loses far less: a dark red house wall of the DTU
    photos, a coloured mode, 2.9 and 0.95; its grey walls 1.9 and 0.96).
    """
    X = lab_blurred[sample]
    n = X.shape[0]
    take = np.linspace(0, n - 1, min(n, 5000)).astype(np.int64)
    X = np.ascontiguousarray(X[take], dtype=np.float32)
    k = int(min(_N_MODES, max(1, X.shape[0] // 50)))
    cv2.setRNGSeed(12345)
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.2)
    _, labels, centres = cv2.kmeans(X, k, None, crit, 1, cv2.KMEANS_PP_CENTERS)
    labels = labels.ravel()
    contrast = None
    if kind == "image border" and lab_raw is not None:
        # only the ring's pixels are needed: the contrast of four strips around it, of
        # the image as it is and smoothed over a pixel (_FLAT_SMOOTH_PX)
        rw = int(max(np.count_nonzero(sample[:, sample.shape[1] // 2]) // 2, 1)) + 3
        contrast = _ring_contrast(lab_raw, sample, rw)[take]
        contrast_smooth = _ring_contrast(lab_raw, sample, rw, _FLAT_SMOOTH_PX)[take]
        vv, uu = np.nonzero(sample)
        bins = _ring_bins(vv[take], uu[take], sample.shape, rw - 3)
    modes, flatness = [], []
    for j in range(k):
        members = labels == j
        if np.count_nonzero(members) < max(10, 0.01 * X.shape[0]):
            continue
        cov = np.cov(X[members].T.astype(np.float64)) + _SIGMA0_LAB ** 2 * np.eye(3)
        whiten = np.linalg.cholesky(np.linalg.inv(cov))  # inv(cov) = W W^T
        mode = (centres[j].astype(np.float64), whiten)
        if contrast is not None:
            flat = float(np.median(contrast[members]))
            flat_smooth = float(np.median(contrast_smooth[members]))
            chroma = float(np.hypot(centres[j][1], centres[j][2]))
            limit = _FLAT_NEUTRAL if chroma < _NEUTRAL_CHROMA else _FLAT_COLOURED
            flatness.append((flat / limit, flat_smooth / limit, _surrounds(bins, members),
                             mode, chroma < _NEUTRAL_CHROMA))
            continue
        modes.append(mode)
    if flatness:  # noise makes every mode rough: then keep those nearly as flat as the flattest
        cut = max(1.0, 1.5 * min(r for r, _, _, _, _ in flatness))
        modes = [m for r, rs, around, m, neutral in flatness
                 if r <= cut or (around and r <= _SURROUND_ROUGH)
                 or (neutral and r >= _NOISE_RATIO * rs
                     and rs <= (_SURROUND_ROUGH if around else 1.0))]
    return modes


def _ring_contrast(lab: np.ndarray, sample: np.ndarray, rw: int, sigma: float = 0.0
                   ) -> np.ndarray:
    """:func:`_local_contrast` of ``lab`` at the ``sample`` pixels of the image border
    ring, from four strips ``rw`` pixels wide (only those are computed), each smoothed
    first by a Gaussian of ``sigma`` pixels when ``sigma`` > 0."""
    def of(strip: np.ndarray) -> np.ndarray:
        if sigma > 0:
            strip = cv2.GaussianBlur(np.ascontiguousarray(strip), (0, 0), sigmaX=sigma,
                                     borderType=cv2.BORDER_REPLICATE)
        return _local_contrast(strip)

    full = np.zeros(sample.shape, np.float32)
    full[:rw] = of(lab[:rw])
    full[-rw:] = of(lab[-rw:])
    full[:, :rw] = of(lab[:, :rw])
    full[:, -rw:] = of(lab[:, -rw:])
    return full[sample]


_RING_BINS = 64  # the image border ring's length in bins (16 per side)


def _ring_bins(v: np.ndarray, u: np.ndarray, shape: tuple[int, int], ring: int) -> np.ndarray:
    """Bin (0 .. ``_RING_BINS`` - 1) of ring pixels ``(v, u)`` along the image's border,
    clockwise from the top-left corner, a quarter of the bins per side."""
    h, w = shape
    q = _RING_BINS // 4
    top, right, bottom = v < ring, u >= w - ring, v >= h - ring
    pos = np.where(top, u / w, np.where(right, 1 + v / h, np.where(
        bottom, 2 + (w - 1 - u) / w, 3 + (h - 1 - v) / h)))
    return np.clip((pos * q).astype(np.int64), 0, _RING_BINS - 1)


def _surrounds(bins: np.ndarray, members: np.ndarray) -> bool:
    """Whether a mode runs around the image along its border ring: on at least
    ``_SURROUND_SIDES`` sides (a side: at least 30 % of its bins have at least 10 % of
    their pixels in the mode), or in at least ``_SURROUND_RING`` of all the ring's bins.

    Why: a ring sample may hold the object where the frame cuts it off, so only flat
    modes are background there; but a table printed with markers is rough at the scale
    of the flatness test (paper between the marks: 1.15-1.42 times the flat limit on
    simulated cells) and, in the views where the wall fills the top, it was left out of
    the background: the table became the object (the views' masks IoU 0.18-0.32 against
    the truth). A mode that runs around the image is what surrounds the object (the
    table, the room), not the object cut off by the frame: on the real DTU scan 24 (49
    views, their true masks) no object mode is in 30 % of the ring's bins, and the two
    that run along three sides (views 4 and 6, whose object fills the frame) are 1.9 and
    2.3 times the limit (``benchmarks/README.md``, stop 40)."""
    share = (np.bincount(bins[members], minlength=_RING_BINS)
             / np.maximum(np.bincount(bins, minlength=_RING_BINS), 1)) >= 0.1
    sides = int((share.reshape(4, -1).mean(axis=1) >= 0.3).sum())
    return sides >= _SURROUND_SIDES or float(share.mean()) >= _SURROUND_RING


def _mode_distance(lab: np.ndarray, modes: list[tuple[np.ndarray, np.ndarray]]
                   ) -> np.ndarray:
    best = None
    for mean, whiten in modes:
        wt = whiten.T  # z = W^T (x - mean): an affine map per pixel (cv2.transform, SIMD)
        m = np.hstack([wt, -(wt @ mean)[:, None]]).astype(np.float32)
        z = cv2.transform(lab, m)
        q = cv2.transform(cv2.multiply(z, z), _ONES_1x3)
        best = q if best is None else np.minimum(best, q)
    return np.sqrt(best)


def colour_difference(
    image: np.ndarray,
    sample: np.ndarray,
    *,
    blur_sigma_px: float = 1.0,
    border_sample: bool = False,
    _keep_model: dict | None = None,
) -> np.ndarray:
    """How far each pixel's colour is from the background's (the automatic polarity).

    The background is modelled from the pixels of ``sample`` in CIE L*a*b* as a few
    colour modes (k-means), each with its own covariance; the feature is the Mahalanobis
    distance of a pixel's (blurred) colour to the nearest mode, in the modes' standard
    deviations. An object differs from the background in lightness, in hue, or both:
    brighter, darker, coloured on white, grey on colour.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    sample : (H, W) bool
        Pixels known (or taken) to be background.
    blur_sigma_px : float
        Gaussian blur of the Lab image before modelling and measuring.
    border_sample : bool
        The sample is the image's border and may hold part of the object: keep only its
        flat modes (see :func:`_background_modes`).

    Returns
    -------
    difference : (H, W) float32, >= 0

    References
    ----------
    P. C. Mahalanobis, "On the generalized distance in statistics", 1936; S. Lloyd,
    "Least squares quantization in PCM", IEEE Trans. IT 28(2), 1982 (k-means); D. Arthur,
    S. Vassilvitskii, "k-means++", SODA 2007.
    """
    raw = to_lab(image)
    sample = np.asarray(sample, dtype=bool)
    if sample.shape != raw.shape[:2]:
        raise ValueError(f"sample must be (H, W) bool of the image's size {raw.shape[:2]}, "
                         f"got {sample.shape}")
    if np.count_nonzero(sample) < 10:
        raise StageError("silhouette: fewer than 10 background pixels to model the "
                         "background's colour from")
    lab = raw if blur_sigma_px <= 0 else cv2.GaussianBlur(
        raw, (0, 0), sigmaX=float(blur_sigma_px), borderType=cv2.BORDER_REPLICATE)
    if not border_sample:
        # model the background's colours, not the blends along its edges: a printed marker's
        # blurred rim spans every grey between paper and ink, and would make any grey
        # object look like the table
        contrast = _local_contrast(lab)
        c = contrast[sample]
        flat = sample & (contrast <= max(3.0 * float(np.median(c)), 2.0))
        if np.count_nonzero(flat) >= max(100, 0.3 * np.count_nonzero(sample)):
            sample = flat
    modes = _background_modes(lab, sample, "image border" if border_sample else "outside roi",
                              raw)
    d = _mode_distance(lab, modes)
    if _keep_model is not None:
        _keep_model.update(lab=lab, modes=modes)
    return d


def _per_colour(x: np.ndarray, distance) -> np.ndarray:
    """``distance`` of colours ``x`` (N, 3, Lab) evaluated once per distinct colour (1 Lab
    unit bins: a ROI holds far fewer colours than pixels), (N,)."""
    xq = np.rint(np.asarray(x, dtype=np.float32)).astype(np.int64)
    keys = (xq[:, 0] * 512 + xq[:, 1] + 256) * 512 + xq[:, 2] + 256
    uniq, inverse = np.unique(keys, return_inverse=True)
    u = np.stack([uniq // (512 * 512), (uniq // 512) % 512 - 256, uniq % 512 - 256], axis=1)
    return distance(u.astype(np.float32))[inverse.ravel()]


def _blend_distance(x: np.ndarray, modes: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Distance (Lab units) of colours ``x`` (N, 3) to the nearest segment between two
    background modes (the colours of a blurred edge between two background colours, or
    of a background colour darkened towards another by a shadow); all pairs at once."""
    return _per_colour(x, lambda u: _segment_distance(u, modes))


def _shadow_distance(x: np.ndarray, modes: list[tuple[np.ndarray, np.ndarray]],
                     darkest: float) -> np.ndarray:
    """Distance (Lab units) of colours ``x`` (N, 3) to the nearest background mode darkened
    towards black down to ``darkest`` of its Lab coordinates (a shadow on it: the same
    hue, less light)."""
    def darkened(u: np.ndarray) -> np.ndarray:
        d = np.full(len(u), np.inf, np.float32)
        for m, _ in modes:  # a few modes
            a = np.asarray(m, dtype=np.float32)
            ab = (np.float32(darkest) - 1) * a
            t = np.clip(((u - a) @ ab) / max(float(ab @ ab), 1e-6), 0.0, 1.0)
            np.minimum(d, np.linalg.norm(u - a - t[:, None] * ab, axis=1), out=d)
        return d

    return _per_colour(x, darkened)


def _segment_distance(x: np.ndarray, modes: list[tuple[np.ndarray, np.ndarray]]
                      ) -> np.ndarray:
    means = np.array([m for m, _ in modes], dtype=np.float32)
    i, j = np.triu_indices(len(means), k=1)
    a, ab = means[i], means[j] - means[i]                      # (P, 3)
    x = np.asarray(x, dtype=np.float32)
    g = x @ means.T                                            # (N, k)
    xa = g[:, i]                                               # x . a
    p = g[:, j] - xa - (a * ab).sum(axis=1)                    # (x - a) . ab
    length2 = np.maximum((ab * ab).sum(axis=1), np.float32(1e-6))  # |ab|^2
    q = (x * x).sum(axis=1)[:, None] - 2.0 * xa + (a * a).sum(axis=1)  # |x - a|^2
    t = p / length2
    np.clip(t, 0.0, 1.0, out=t)
    q -= t * (2.0 * p - t * length2)                           # |x - a - t ab|^2
    return np.sqrt(np.maximum(q.min(axis=1), 0.0))


def _as_uint8_rgb(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[..., 0]
    if a.dtype == np.uint8:
        u8 = a
    elif a.dtype == np.uint16:
        u8 = (a.astype(np.float32) / 257.0 + 0.5).astype(np.uint8)
    else:
        u8 = (np.clip(a.astype(np.float32), 0, 1) * 255.0 + 0.5).astype(np.uint8)
    if u8.ndim == 2:
        u8 = np.repeat(u8[..., None], 3, axis=2)
    return np.ascontiguousarray(u8)


def refine_with_grabcut(
    image: np.ndarray,
    mask: np.ndarray,
    roi: tuple[int, int, int, int] | None = None,
    *,
    max_side_px: int = 640,
    band_px: int = 24,
    iterations: int = 1,
    background: np.ndarray | None = None,
) -> np.ndarray:
    """Refine a silhouette's outline with GrabCut (Rother et al. 2004), seeded by the mask.

    The image is reduced so that its longer side is at most ``max_side_px`` (GrabCut's
    cost grows with the pixels and with the number of undecided ones). At that scale the
    mask eroded by ``band_px / 2`` is sure object, the mask is probable object, a band of
    ``band_px`` around it probable background, everything farther and everything outside
    the ROI sure background, and so is ``background`` (what the colour model already
    decided is background: a shadow or a marker's rim beside the object, whose dark
    colours GrabCut's mixtures would otherwise give to a dark face next to them); only
    the crop around the undecided band is cut. GrabCut then
    fits colour mixtures (5 Gaussians each) to object and background and cuts along
    colour edges: the outline follows the object's edge where the threshold was off by a
    shadow, a reflection or a shaded part near the background's colour. The result is
    resized back (bilinear on the 0/1 labels, cut at 1/2).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    mask : (H, W) bool
        The first silhouette.
    roi : (u0, v0, u1, v1) int, optional
        Nothing outside it is object.
    max_side_px, band_px, iterations : int
        Working size, undecided band (pixels at the working size), GrabCut iterations.
    background : (H, W) bool, optional
        Pixels outside the mask that are known background (sure background for GrabCut).

    Returns
    -------
    mask : (H, W) bool

    References
    ----------
    C. Rother, V. Kolmogorov, A. Blake, "GrabCut: interactive foreground extraction using
    iterated graph cuts", ACM Trans. Graphics 23(3), 2004 (SIGGRAPH).
    """
    m = np.asarray(mask, dtype=bool)
    rgb = _as_uint8_rgb(image)
    height, width = m.shape
    if rgb.shape[:2] != m.shape:
        raise ValueError(f"mask must have the image's size {rgb.shape[:2]}, got {m.shape}")
    if roi is not None:  # nothing outside the ROI, whatever GrabCut does
        u0, v0, u1, v1 = _check_roi(roi, width, height)
        clipped = np.zeros_like(m)
        clipped[v0:v1, u0:u1] = m[v0:v1, u0:u1]
        m = clipped
    if not m.any():
        return m.copy()
    scale = min(1.0, float(max_side_px) / max(height, width))
    if scale < 1.0:
        sw, sh = max(1, int(round(width * scale))), max(1, int(round(height * scale)))
        small = cv2.resize(rgb, (sw, sh), interpolation=cv2.INTER_AREA)
        mk = cv2.resize(m.view(np.uint8), (sw, sh), interpolation=cv2.INTER_NEAREST)
    else:
        sw, sh, small, mk = width, height, rgb, m.view(np.uint8).copy()

    def disc(r: int) -> np.ndarray:
        return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))

    core = cv2.erode(mk, disc(max(1, band_px // 2)))
    near = cv2.dilate(mk, disc(band_px))
    labels = np.full((sh, sw), cv2.GC_BGD, np.uint8)
    labels[near > 0] = cv2.GC_PR_BGD
    labels[mk > 0] = cv2.GC_PR_FGD
    labels[core > 0] = cv2.GC_FGD
    if background is not None:
        sure = np.asarray(background, dtype=bool)
        if sure.shape != m.shape:
            raise ValueError(f"background must have the mask's size {m.shape}, got {sure.shape}")
        if scale < 1.0:  # a working pixel any of whose pixels is known background
            sure = cv2.resize(sure.view(np.uint8), (sw, sh), interpolation=cv2.INTER_AREA) > 0
        labels[sure & (mk == 0)] = cv2.GC_BGD
    if roi is not None:
        keep = np.zeros((sh, sw), bool)
        keep[int(np.floor(v0 * scale)):int(np.ceil(v1 * scale)),
             int(np.floor(u0 * scale)):int(np.ceil(u1 * scale))] = True
        labels[~keep] = cv2.GC_BGD
    undecided = (labels == cv2.GC_PR_BGD) | (labels == cv2.GC_PR_FGD)
    if not undecided.any() or not (labels == cv2.GC_FGD).any() \
            or not np.isin(labels, (cv2.GC_BGD, cv2.GC_PR_BGD)).any():
        return m.copy()
    vs, us = np.nonzero(undecided)
    pad = band_px + 2
    r0, r1 = max(vs.min() - pad, 0), min(vs.max() + pad + 1, sh)
    c0, c1 = max(us.min() - pad, 0), min(us.max() + pad + 1, sw)
    crop = np.ascontiguousarray(labels[r0:r1, c0:c1])
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    try:
        cv2.grabCut(np.ascontiguousarray(small[r0:r1, c0:c1, ::-1]), crop, None, bgd, fgd,
                    int(iterations), cv2.GC_INIT_WITH_MASK)
    except cv2.error as exc:  # e.g. one class has too few pixels for its mixture
        _log.debug("grabcut skipped: %s", exc)
        return m.copy()
    labels[r0:r1, c0:c1] = crop
    fg = ((labels == cv2.GC_FGD) | (labels == cv2.GC_PR_FGD)).astype(np.float32)
    if scale < 1.0:
        fg = cv2.resize(fg, (width, height), interpolation=cv2.INTER_LINEAR)
    out = fg > 0.5
    if roi is not None:
        inside = np.zeros_like(out)
        inside[v0:v1, u0:u1] = True
        out &= inside
    return out


def _nearest_colour(colour: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """For every pixel, ``colour`` at the nearest pixel of ``seed`` (bool, not empty):
    one distance transform with per-pixel labels (OpenCV, 5 x 5 chamfer metric)."""
    src = np.where(seed, np.uint8(0), np.uint8(1))
    _, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    vs, us = np.nonzero(seed)
    lut = np.zeros((int(labels.max()) + 1, colour.shape[2]), np.float32)
    lut[labels[vs, us]] = colour[vs, us]
    return lut[labels]


def refine_edges(
    image: np.ndarray,
    mask: np.ndarray,
    roi: tuple[int, int, int, int] | None = None,
    *,
    reach_px: int = 3,
    min_contrast: float = 0.06,
) -> np.ndarray:
    """Put a silhouette's outline on the object's edge at full resolution: each pixel
    within ``reach_px`` of the outline is object when its colour is nearer the object's
    than the background's next to it.

    For a pixel of that band, ``F`` is the (slightly blurred, σ = 1 px) colour of the
    nearest pixel that is object ``reach_px`` deep inside the mask and ``B`` that of the
    nearest pixel ``reach_px`` outside it: the two colours the pixel blends. The pixel's
    RGB colour ``c`` gives the blend's fraction ``α = (c - B)·(F - B) / |F - B|²`` (the
    two-colour model of alpha matting, Chuang et al. 2001, with the colours taken from the
    nearest sure pixels, as in Wang & Cohen's local sampling); the pixel is object when
    ``α > 1/2``: the outline passes where the ray through the pixel's centre leaves the
    object, whatever each side's colour — on white paper or black ink of a marker, in a
    shadow, on a dark backdrop. Where ``|F - B|`` is below ``min_contrast`` (of the 0-1
    RGB scale) the two sides look alike, and where ``c`` is no blend of the two (``α``
    outside [-1/2, 3/2], or farther than ``|F - B| / 2`` from their segment: texture the
    nearest sure pixels do not show), the pixel keeps its label. A mask more than
    ``reach_px`` off is not moved farther than that.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    mask : (H, W) bool
    roi : (u0, v0, u1, v1) int, optional
        Nothing outside it is object.
    reach_px : int
        Half-width of the band that may change (pixels).
    min_contrast : float
        Smallest RGB distance (0-1 scale) of object and background colour that decides.

    Returns
    -------
    mask : (H, W) bool

    References
    ----------
    Y.-Y. Chuang, B. Curless, D. H. Salesin, R. Szeliski, "A Bayesian approach to digital
    matting", CVPR 2001; J. Wang, M. F. Cohen, "Optimized color sampling for robust
    matting", CVPR 2007.
    """
    m = np.asarray(mask, dtype=bool)
    rgb8 = _as_uint8_rgb(image)
    height, width = m.shape
    if rgb8.shape[:2] != m.shape:
        raise ValueError(f"mask must have the image's size {rgb8.shape[:2]}, got {m.shape}")
    reach = int(reach_px)
    vs, us = np.nonzero(m)
    if reach <= 0 or vs.size == 0:
        return m.copy()
    pad = 3 * reach + 4  # the crop around the mask holds its outer side's colours
    r0, r1 = max(int(vs.min()) - pad, 0), min(int(vs.max()) + pad + 1, height)
    c0, c1 = max(int(us.min()) - pad, 0), min(int(us.max()) + pad + 1, width)
    mc = np.ascontiguousarray(m[r0:r1, c0:c1])
    rgb = rgb8[r0:r1, c0:c1].astype(np.float32) * np.float32(1.0 / 255.0)
    ref = cv2.GaussianBlur(rgb, (0, 0), sigmaX=1.0, borderType=cv2.BORDER_REPLICATE)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * reach + 1, 2 * reach + 1))
    inner = cv2.erode(mc.view(np.uint8), disc, borderType=cv2.BORDER_REPLICATE) > 0
    outer = cv2.erode((~mc).view(np.uint8), disc, borderType=cv2.BORDER_REPLICATE) > 0
    if not inner.any() or not outer.any():
        return m.copy()
    band = ~inner & ~outer
    fg = _nearest_colour(ref, inner)[band]
    bg = _nearest_colour(ref, outer)[band]
    fb = fg - bg
    n2 = (fb * fb).sum(axis=1)
    cb = rgb[band] - bg
    alpha = (cb * fb).sum(axis=1) / np.maximum(n2, np.float32(1e-9))
    # a colour off the blend's segment is neither (texture of either side that the
    # nearest sure pixels do not show): it keeps its label
    off = cb - alpha[:, None] * fb
    decided = (n2 > np.float32(min_contrast) ** 2) & (alpha >= -0.5) & (alpha <= 1.5) \
        & ((off * off).sum(axis=1) <= 0.25 * n2)
    labels = mc[band]
    labels[decided] = alpha[decided] > 0.5
    out = m.copy()
    crop = out[r0:r1, c0:c1]
    crop[band] = labels
    if roi is not None:
        u0, v0, u1, v1 = _check_roi(roi, width, height)
        inside = np.zeros_like(out)
        inside[v0:v1, u0:u1] = True
        out &= inside
    return out


# ---------------------------------------------------------------------- quality
QA_FLAGS = ("fills_region", "touches_all_sides", "inverted", "surrounds_view")
_FILL_LIMIT = 0.95
#: :func:`surrounding_views`: a mask that reaches all four sides of its image and covers
#: more than this share of it surrounds the view ...
_SURROUND_FILL = 0.5
#: ... and when more than this share of a scan's views do, they are flagged
_SURROUND_VIEWS = 0.5


def surrounding_views(masks: Sequence[np.ndarray]) -> list[int]:
    """The views flagged ``surrounds_view``: those whose mask reaches all four sides of
    the image and covers more than :data:`_SURROUND_FILL` of it, when they are more than
    :data:`_SURROUND_VIEWS` of the views with a mask; else none.

    One such view is an object larger than the frame: DTU scan 24's house fills 5 of its
    49 views so, 63-80 % of the image, and the published masks agree. A scan taken
    around an object shows it whole in most views, so when most of its masks surround
    their views the segmentation took the surroundings for the object, with the object
    a hole in them: the table and the wall around a black bottle on a table printed
    with black dots (random scene 711: the dots the only flat colour of the image's
    border, so the only background; masks of IoU 0.00-0.01, fill 0.81-0.85), a grey blob
    and a green cup on checker tables (517, 529: 0.19-0.27). Those masks agree with each
    other, as the table agrees with itself: their hull, the table's slab, placed the
    workspace of a recording without a box and kept the table's laser points as
    measured surface (711: 56.7 mm from the truth at the median) or closed 99 % of the
    mesh (517: 59 mm). A flagged view does not judge the laser's points, and a hull that
    only flagged views carve is not made when the scan has laser frames
    (:func:`robo3d.stages.carve.stage_carve`).
    """
    fills = []
    for i, m in enumerate(masks):
        m = np.asarray(m, dtype=bool)
        if not m.any():
            continue
        around = bool(m[:, 0].any() and m[0, :].any() and m[:, -1].any() and m[-1, :].any())
        fills.append((i, around and np.count_nonzero(m) > _SURROUND_FILL * m.size))
    flagged = [i for i, f in fills if f]
    return flagged if len(flagged) > _SURROUND_VIEWS * len(fills) else []


def silhouette_qa(mask: np.ndarray, roi: tuple[int, int, int, int] | None,
                  difference: np.ndarray | None = None) -> dict:
    """Flags of an absurd silhouette (one no object in the workspace can cast).

    - ``fills_region``: the mask covers more than 95 % of the region analysed;
    - ``touches_all_sides``: it reaches all four sides of its region, and at least one of
      them lies inside the image (the projected workspace box's own edge, margin
      included: an object inside the box cannot reach it on every side). An object larger
      than the frame touches the image's four sides legitimately, which is reported as
      ``touches_image_border``, not here;
    - ``inverted``: the pixels the mask calls object look more like the background than
      those it calls background (median colour difference, :func:`colour_difference`,
      inside the mask not above the median in the rest of the region).

    Parameters
    ----------
    mask : (H, W) bool
    roi : (u0, v0, u1, v1) int or None (the whole image)
    difference : (H, W) float, optional
        The colour difference to the background; without it ``inverted`` is not checked.

    Returns
    -------
    qa : dict
        ``flags`` (list of str, from :data:`QA_FLAGS`), ``fill_fraction`` (mask pixels /
        region pixels), ``sides_touched`` (of ``left, top, right, bottom``),
        ``difference_inside`` / ``difference_outside`` (medians, or None).
    """
    m = np.asarray(mask, dtype=bool)
    height, width = m.shape
    u0, v0, u1, v1 = (0, 0, width, height) if roi is None else _check_roi(roi, width, height)
    region = m[v0:v1, u0:u1]
    fill = float(np.count_nonzero(region)) / float(region.size)
    sides = {"left": bool(region[:, 0].any()), "top": bool(region[0, :].any()),
             "right": bool(region[:, -1].any()), "bottom": bool(region[-1, :].any())}
    inner = {"left": u0 > 0, "top": v0 > 0, "right": u1 < width, "bottom": v1 < height}
    flags = []
    if fill > _FILL_LIMIT:
        flags.append("fills_region")
    if all(sides.values()) and any(inner.values()):
        flags.append("touches_all_sides")
    d_in = d_out = None
    if difference is not None and region.any() and not region.all():
        d = np.asarray(difference)[v0:v1, u0:u1]
        d_in, d_out = float(np.median(d[region])), float(np.median(d[~region]))
        if d_in <= d_out:
            flags.append("inverted")
    return {"flags": flags, "fill_fraction": round(fill, 4),
            "sides_touched": [k for k, v in sides.items() if v],
            "difference_inside": None if d_in is None else round(d_in, 3),
            "difference_outside": None if d_out is None else round(d_out, 3)}


@dataclass(frozen=True)
class SegmentOptions(Options):
    """The segmentation's parameters: the config's ``segmentation`` keys that
    :func:`segment_view` and :func:`segment_silhouette` use, under the same names.

    The section's other keys (``background_topic``, ``background_max_offset_mm``,
    ``background_max_offset_deg``) are the stage's: which empty-scene image goes with a
    view. :func:`segment_silhouette` reads the first nine fields and ``shadow_darkest``;
    the three ``roi_*`` fields say how :func:`segment_view` finds the region it
    analyses.

    Attributes
    ----------
    polarity : {"auto", "brighter", "darker"}
        ``"auto"``: the object is what differs in colour from the background, modelled
        from the pixels outside the ROI (or the image border), see
        :func:`colour_difference`. ``"brighter"`` / ``"darker"``: the seed's grey
        threshold, object where the grey value is above (``f > s``) or below (``f < s``).
        With a background image the feature is the difference to the empty scene
        (colour with ``"auto"``, grey otherwise).
    threshold : float or None
        ``s``: on the 0–255 grey scale for ``brighter``/``darker`` and grey background
        subtraction; in the background's standard deviations (colour difference) for
        ``auto``; in CIE Lab units (ΔE) for colour background subtraction. None: chosen
        per view (Otsu; see the module docstring).
    blur_sigma_px : float, pixels
        Gaussian blur before thresholding; 0 for none.
    min_component_px : int, pixels
        Foreground components with fewer pixels are specks and are removed.
    min_component_fraction : float
        Components smaller than this fraction of the largest one are removed too.
    fill_holes : bool
        Fill the background regions enclosed by the object (the silhouette is the whole
        projected region).
    max_hole_fraction : float
        Enclosed background regions larger than this fraction of the silhouette's area
        are see-through gaps and stay background (1.0 fills every hole, as the seed does).
    grabcut : bool
        Refine the outline with GrabCut seeded by the thresholded mask
        (:func:`refine_with_grabcut`).
    edge_refine_px : int, pixels
        Move the outline onto the object's colour edge within this many pixels, at full
        resolution (:func:`refine_edges`); 0 for none.
    roi_from_workspace : bool
        :func:`segment_view`: analyse only the projected workspace box when there is one.
    roi_auto : bool
        :func:`segment_view`: without a box, find the object's region first
        (:func:`find_roi`).
    roi_margin_px : int, pixels
        Margin around the projected box or the found region.
    shadow_darkest : float
        Automatic polarity with a sample outside the ROI: foreground whose colour is a
        background colour darkened down to this fraction of its Lab coordinates is a
        shadow on the table and dropped, when the object's other colours are unlike the
        background's or far darker (:func:`_shadows`); 1 keeps shadows.
    """

    section = "segmentation"

    polarity: str = "auto"
    threshold: float | None = None
    blur_sigma_px: float = 1.0
    min_component_px: int = 200
    min_component_fraction: float = 0.01
    fill_holes: bool = True
    max_hole_fraction: float = 0.02
    grabcut: bool = True
    edge_refine_px: int = 3
    roi_from_workspace: bool = True
    roi_auto: bool = True
    roi_margin_px: int = 10
    shadow_darkest: float = 0.55


def _check_options(o: SegmentOptions) -> None:
    """``ValueError`` naming the first option of :func:`segment_silhouette` out of range."""
    if o.polarity not in _POLARITIES:
        raise ValueError(f"polarity must be one of {_POLARITIES}, got {o.polarity!r}")
    if not np.isfinite(o.blur_sigma_px) or o.blur_sigma_px < 0:
        raise ValueError(f"blur_sigma_px must be >= 0, got {o.blur_sigma_px}")
    if int(o.min_component_px) < 0:
        raise ValueError(f"min_component_px must be >= 0, got {o.min_component_px}")
    if not 0.0 <= float(o.min_component_fraction) <= 1.0:
        raise ValueError(f"min_component_fraction must be in [0, 1], "
                         f"got {o.min_component_fraction}")
    if not 0.0 <= float(o.max_hole_fraction):
        raise ValueError(f"max_hole_fraction must be >= 0, got {o.max_hole_fraction}")
    if o.threshold is not None and not np.isfinite(o.threshold):
        raise ValueError(f"threshold must be finite, got {o.threshold}")
    if int(o.edge_refine_px) < 0:
        raise ValueError(f"edge_refine_px must be >= 0, got {o.edge_refine_px}")
    if not 0.0 < float(o.shadow_darkest) <= 1.0:
        raise ValueError(f"shadow_darkest must be in (0, 1], got {o.shadow_darkest}")


def _feature(image: np.ndarray, grey: np.ndarray, background: np.ndarray | None,
             box: tuple[int, int, int, int], sample: np.ndarray, sample_kind: str,
             o: SegmentOptions) -> tuple[np.ndarray, str, np.ndarray | None, dict]:
    """The feature ``f`` that is thresholded (module docstring, steps 1-3 and C), its
    mode (``polarity``, or ``"difference"`` with a background image), the colour
    difference to the background model when that is the feature (for QA), and the
    model (modes, Lab image) of the automatic polarity (empty otherwise)."""
    u0, v0, u1, v1 = box
    f = grey
    height, width = f.shape
    mode = o.polarity
    difference = None  # colour difference to the background model (auto, and for QA)
    model: dict = {}
    if background is not None:
        if np.asarray(background).shape[:2] != f.shape:
            b = np.asarray(background)
            raise ValueError(f"background must have the image's size {width}x{height}, "
                             f"got {b.shape[1] if b.ndim > 1 else '?'}x{b.shape[0]}")
        if o.polarity == "auto":
            lab, lab_bg = to_lab(image), to_lab(background, name="background")
            f = np.sqrt(((lab - lab_bg) ** 2).sum(axis=2)).astype(np.float32)
        else:
            f = np.abs(f - to_grey(background, name="background"))
        mode = "difference"
    else:
        inside_grey = f[v0:v1, u0:u1]
        if o.threshold is None and float(inside_grey.max()) - float(inside_grey.min()) <= 1e-6:
            raise StageError(f"silhouette: the image is uniform (grey "
                             f"{float(inside_grey.min()):.1f}) inside the region analysed, "
                             "so no threshold separates object and background")
        if o.polarity == "auto":
            difference = colour_difference(image, sample, blur_sigma_px=o.blur_sigma_px,
                                           border_sample=sample_kind == "image border",
                                           _keep_model=model)
            f = difference
    if o.blur_sigma_px > 0 and mode != "auto":
        f = cv2.GaussianBlur(f, (0, 0), sigmaX=float(o.blur_sigma_px),
                             borderType=cv2.BORDER_REPLICATE)
    return f, mode, difference, model


def _threshold(f: np.ndarray, box: tuple[int, int, int, int], sample: np.ndarray, mode: str,
               o: SegmentOptions
               ) -> tuple[float, tuple[float, float] | None, np.ndarray | None]:
    """The threshold ``s`` (steps 5 and D), the background's ``(level, edge)`` when known,
    and the per-pixel midpoints of the outline band (None: ``s`` everywhere)."""
    u0, v0, u1, v1 = box
    inside = f[v0:v1, u0:u1]
    local = None
    level = None
    if mode in ("brighter", "darker"):
        level = _background_level(f, box, mode)
    if o.threshold is not None:
        s = float(o.threshold)
    elif o.polarity == "auto":
        # the colour difference (to the background's modes, or to the empty scene) is
        # heavy-tailed: the object's colours lie at many distances from the background's.
        # Otsu on its logarithm, the outline then cut at its own midpoint
        s = max(float(np.expm1(_otsu(np.log1p(inside.ravel())))), _MIN_THRESHOLD)
    else:
        s = _otsu(inside.ravel())
        if level is not None:
            s_shade = _shade_aware_threshold(inside, s, level, mode)
            if s_shade != s:
                local = _local_midpoint(inside, level, mode, o.blur_sigma_px)
                s = s_shade
    if o.polarity == "auto":  # the background's level and edge (see-through gaps, outline)
        bg = f[sample & (f <= s)]
        if bg.size >= 100:
            med = float(np.median(bg))
            spread = 6.0 * max(1.4826 * float(np.median(np.abs(bg - med))), 0.1)
            level = (med, min(float(np.percentile(bg, 99.5)) + spread, s))
            if o.threshold is None:
                local = _local_midpoint(inside, level, "brighter", o.blur_sigma_px)
    return s, level, local


def _shadows(lab: np.ndarray, fg: np.ndarray, modes: list, darkest: float) -> np.ndarray:
    """The foreground pixels ``fg`` whose colour is a background mode darkened (a shadow
    on the table: :func:`_shadow_distance` within ``_BLEND_LAB``), when most of the rest
    of the foreground is unlike anything a shadow could make: coloured unlike every mode
    (a*b* distance at least ``_SHADOW_CHROMA``), or darker than the darkest shadow by
    far (lightness under ``_SHADOW_DARKER`` times it: a black object); none otherwise. A
    grey or white object's own shading holds the shadow's colours (a grey bracket's lit
    face is the table's grey a little darker, its shaded face as dark as the darkest
    shadow); its shadow stays with it, as before."""
    out = np.zeros_like(fg)
    if not fg.any():
        return out
    out[fg] = _shadow_distance(lab[fg], modes, darkest) <= _BLEND_LAB
    rest = fg & ~out
    if not out.any() or not rest.any():
        return np.zeros_like(fg)
    ab = np.array([m[1:] for m, _ in modes], dtype=np.float32)
    x = lab[rest]
    chroma = np.linalg.norm(x[:, None, 1:] - ab[None], axis=2).min(axis=1)
    darker = x[:, 0] < _SHADOW_DARKER * darkest * min(float(m[0]) for m, _ in modes)
    unlike = float(np.mean((chroma >= _SHADOW_CHROMA) | darker))
    return out if unlike >= 0.5 else np.zeros_like(fg)


def _foreground(inside: np.ndarray, s: float, local: np.ndarray | None, mode: str,
                sample_kind: str, model: dict, box: tuple[int, int, int, int],
                blur_sigma_px: float, shadow_darkest: float = 1.0
                ) -> tuple[np.ndarray, np.ndarray | None]:
    """The ROI's foreground: ``f`` beyond ``s``, the outline band cut at its local
    midpoints, and (automatic polarity) blends of two background colours and, beside a
    coloured or black object, shadows on the background (:func:`_shadows`, ``shadow_darkest``)
    dropped; and those dropped (None when none were, or when the object has such colours
    and only its rims were dropped): background that GrabCut must not take back."""
    u0, v0, u1, v1 = box
    fg_roi = inside < s if mode == "darker" else inside > s
    dropped = None
    if local is not None:  # refine the outline only: a band along the background
        r = max(2, int(np.ceil(3 * blur_sigma_px)))
        kernel = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
        band = fg_roi & cv2.dilate((~fg_roi).view(np.uint8), kernel).astype(bool)
        fg_roi[band] = (inside[band] < local[band]) if mode == "darker" else \
            (inside[band] > local[band])
    modes = model.get("modes", ()) if mode == "auto" and sample_kind == "outside roi" else ()
    if len(modes) > 1 or (modes and shadow_darkest < 1):
        # colours between two background colours differ from both but are background: the
        # blurred rim of a printed marker (every grey between paper and ink), which would
        # close into rings and then blobs, and a shadow on the table (the table's colour
        # darkened towards the markers' ink). Such foreground is dropped, unless it is most
        # of the foreground (then the object itself is of those colours, a grey object on
        # a black-and-white table): then only the rims, a 2 px band along the background
        lab = model["lab"][v0:v1, u0:u1]
        blend = np.zeros_like(fg_roi)
        if len(modes) > 1:
            blend[fg_roi] = _blend_distance(lab[fg_roi], modes) <= _BLEND_LAB
        if shadow_darkest < 1:
            blend |= _shadows(lab, fg_roi & ~blend, modes, shadow_darkest)
        if np.count_nonzero(blend) > 0.5 * np.count_nonzero(fg_roi):
            blend &= cv2.dilate((~fg_roi).view(np.uint8), np.ones((5, 5), np.uint8)
                                ).astype(bool)
        elif blend.any():
            dropped = blend
        fg_roi &= ~blend
    return fg_roi, dropped


def _clean(m: np.ndarray, f: np.ndarray, s_bg: float | None, hole_mode: str,
           o: SegmentOptions, where: str) -> tuple[np.ndarray, int, int]:
    """Holes filled (step 6) and specks removed (step 7): the mask, its number of
    components before and of specks removed."""
    if o.fill_holes:
        m = _fill_holes(m, o.max_hole_fraction, f, s_bg, hole_mode)
    n_lab, labels, stats, _ = cv2.connectedComponentsWithStats(m.view(np.uint8),
                                                               connectivity=8)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(np.int64)
    if areas.size == 0:
        raise StageError(f"silhouette is empty after refinement {where}")
    keep_min = max(int(o.min_component_px),
                   int(np.ceil(o.min_component_fraction * areas.max())))
    keep = np.concatenate([[False], areas >= keep_min])
    if not np.any(keep):
        raise StageError(f"silhouette is empty: all {areas.size} foreground components "
                         f"are smaller than {keep_min} px (largest {int(areas.max())} px)"
                         f" {where}")
    return keep[labels], int(areas.size), int(areas.size) - int(np.count_nonzero(keep))


def segment_silhouette(
    image: np.ndarray,
    *,
    roi: tuple[int, int, int, int] | None = None,
    background: np.ndarray | None = None,
    options: SegmentOptions = SegmentOptions(),
    region: np.ndarray | None = None,
) -> Silhouette:
    """Segment the object's silhouette in one view (seed §3.2).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
        The ambient-lit view (RGB if colour).
    roi : (u0, v0, u1, v1) int, optional
        Half-open pixel box (``image[v0:v1, u0:u1]``) outside which everything is
        background; clipped to the image. See :func:`roi_from_box`.
    background : array like ``image``, optional
        The empty scene under the same light and pose.
    options : SegmentOptions
        Polarity, threshold, blur, speck and hole rules, refinements (its ``roi_*``
        fields are :func:`segment_view`'s). Default: the project's defaults.
    region : (H, W) bool, optional
        Where the object can be within the ROI (:func:`region_from_box`: the workspace
        box's projected outline): the ROI's pixels outside it are background, join the
        background's sample (the table next to the object, which the rectangle's frame
        may hardly reach) and are never object.

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
    N. Otsu, IEEE Trans. SMC 9(1), 1979 (threshold selection); C. Rother, V. Kolmogorov,
    A. Blake, ACM Trans. Graphics 23(3), 2004 (GrabCut).
    """
    o = options
    _check_options(o)
    grey = to_grey(image)
    height, width = grey.shape
    if roi is None:
        u0, v0, u1, v1 = 0, 0, width, height
    else:
        u0, v0, u1, v1 = _check_roi(roi, width, height)
    box = (u0, v0, u1, v1)
    sample, sample_kind = _sure_background((height, width), box)
    outside = None
    if region is not None:
        region = np.asarray(region, dtype=bool)
        if region.shape != (height, width):
            raise ValueError(f"region must be {height} x {width} like the image, got "
                             f"{region.shape}")
        outside = ~region
        outside[:v0, :] = outside[v1:, :] = False
        outside[:, :u0] = outside[:, u1:] = False
        if not outside.any():
            outside = None
        elif sample_kind == "outside roi":  # the box's own surroundings inside the ROI
            sample = sample | outside
    f, mode, difference, model = _feature(image, grey, background, box, sample, sample_kind,
                                           o)
    s, level, local = _threshold(f, box, sample, mode, o)
    fg_roi, dropped = _foreground(f[v0:v1, u0:u1], s, local, mode, sample_kind, model, box,
                                  o.blur_sigma_px, o.shadow_darkest)
    if outside is not None:
        fg_roi &= ~outside[v0:v1, u0:u1]
    where = f"(threshold s={s:.2f}, polarity {mode}, roi {box})"
    n_fg = int(np.count_nonzero(fg_roi))
    if n_fg == 0:
        raise StageError(f"silhouette is empty: no pixel passes the threshold {where}")
    if n_fg == fg_roi.size:
        raise StageError(f"silhouette covers every pixel of the region analysed {where}: "
                         "wrong polarity or threshold, or the object fills the view")

    mask = np.zeros((height, width), dtype=bool)
    mask[v0:v1, u0:u1] = fg_roi
    hole_mode = "darker" if mode == "darker" else "brighter"
    s_bg = None if level is None else level[1]
    mask, n_components, n_removed = _clean(mask, f, s_bg, hole_mode, o, where)
    if o.grabcut or o.edge_refine_px > 0:
        known_bg = None
        if dropped is not None:
            known_bg = np.zeros_like(mask)
            known_bg[v0:v1, u0:u1] = dropped
        if outside is not None:
            known_bg = outside.copy() if known_bg is None else known_bg | outside
        refined = refine_with_grabcut(image, mask, box, background=known_bg) if o.grabcut \
            else mask
        if o.edge_refine_px > 0:
            refined = refine_edges(image, refined, box, reach_px=int(o.edge_refine_px))
        if outside is not None:
            refined = refined & ~outside
        try:
            mask = _clean(refined, f, s_bg, hole_mode, o, where)[0]
        except StageError:  # the refinement lost the object: keep the thresholded mask
            _log.debug("refinement left no silhouette %s; the thresholded mask is kept", where)
    if np.all(mask[v0:v1, u0:u1]):
        raise StageError(f"silhouette covers every pixel of the region analysed {where}: "
                         "wrong polarity or threshold, or the object fills the view")
    if difference is None and background is None:
        try:
            difference = colour_difference(image, sample, blur_sigma_px=o.blur_sigma_px,
                                           border_sample=sample_kind == "image border")
        except StageError:
            difference = None
    return _measured(mask, box, s, mode, n_components, n_removed, sample_kind,
                     bool(o.grabcut), silhouette_qa(mask, box, difference))


def _measured(mask: np.ndarray, box: tuple[int, int, int, int], s: float, mode: str,
              n_components: int, n_removed: int, sample_kind: str, refined: bool,
              qa: dict) -> Silhouette:
    """The :class:`Silhouette` of a final mask: its area, centroid, bounding box and
    whether it touches its region's or the image's border."""
    u0, v0, u1, v1 = box
    height, width = mask.shape
    vs, us = np.nonzero(mask)
    area = int(us.size)
    centroid = np.array([us.mean(), vs.mean()], dtype=np.float64)
    bbox = (int(us.min()), int(vs.min()), int(us.max()) + 1, int(vs.max()) + 1)
    touches = bool(bbox[0] <= u0 or bbox[1] <= v0 or bbox[2] >= u1 or bbox[3] >= v1)
    touches_image = bool(bbox[0] == 0 or bbox[1] == 0 or bbox[2] == width
                         or bbox[3] == height)
    _log.debug("silhouette: s=%.2f (%s), %d px, %d components (%d specks removed)%s%s",
               s, mode, area, n_components, n_removed, ", touches border" if touches else "",
               f", QA flags {qa['flags']}" if qa["flags"] else "")
    return Silhouette(mask=mask, threshold=s, polarity=mode, area_px=area,
                      n_components=n_components, touches_border=touches,
                      centroid_uv=centroid, bbox=bbox, touches_image_border=touches_image,
                      roi=box, background_sample=sample_kind, refined=refined, qa=qa)


def find_roi(
    image: np.ndarray,
    *,
    background: np.ndarray | None = None,
    options: SegmentOptions = SegmentOptions(),
) -> tuple[int, int, int, int]:
    """The object's region in a view without a workspace box (seed §3.2, fig. 10).

    A first segmentation of the whole image (:func:`segment_silhouette` with ``options``
    but without GrabCut and the edge refinement: they only move the outline, which the
    margin covers) is reduced to its largest 8-connected component, the object; its
    bounding box grown on every side by the larger of ``options.roi_margin_px`` and 10 %
    of its size, clipped to the image, is the ROI of the final segmentation. Bright
    clutter far from the object is then outside the region, and the threshold is chosen
    from the object and its surroundings only.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    background : array like ``image``, optional
        The empty scene, as for :func:`segment_silhouette`.
    options : SegmentOptions
        The segmentation's options; ``roi_margin_px`` is the least growth of the box,
        pixels, on each side.

    Returns
    -------
    roi : (u0, v0, u1, v1) int
        Half-open pixel box, ``image[v0:v1, u0:u1]``.

    Raises
    ------
    ValueError
        Bad arguments (as :func:`segment_silhouette`).
    StageError
        The first segmentation finds nothing (as :func:`segment_silhouette`).
    """
    margin_px = options.roi_margin_px
    if int(margin_px) < 0:
        raise ValueError(f"roi_margin_px must be >= 0, got {margin_px}")
    first = segment_silhouette(image, background=background,
                               options=options.replace(grabcut=False, edge_refine_px=0))
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
def _edge_samples(box_min: np.ndarray, box_max: np.ndarray, n: int = 9) -> np.ndarray:
    """Points along the 12 edges of an axis-aligned box, (12 n, 3)."""
    corners = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], float)
    edges = [(a, b) for a in range(8) for b in range(a + 1, 8)
             if np.abs(corners[a] - corners[b]).sum() == 1]
    t = np.linspace(0.0, 1.0, n)[:, None]
    unit = np.concatenate([corners[a] + t * (corners[b] - corners[a]) for a, b in edges])
    return box_min + unit * (box_max - box_min)


def _projected_box_edges(lo: np.ndarray, hi: np.ndarray, camera: CameraModel,
                         T: np.ndarray) -> np.ndarray | None:
    """The box's edges (:func:`_edge_samples`) projected with distortion, (12 n, 2)
    pixels; None when its image is unbounded (part of it behind the camera, or beyond
    the radius where the lens model is monotonic). StageError when all of it lies
    behind the camera."""
    pts = _edge_samples(lo, hi)
    uv, in_front = project_points(pts, camera, T)
    if not np.any(in_front):
        raise StageError(f"workspace box {lo}..{hi} is entirely behind camera "
                         f"{camera.frame_id!r}")
    if not np.all(in_front):
        return None
    t_cb = invert_transform(T)
    pc = pts @ t_cb[:3, :3].T + t_cb[:3, 3]
    if np.any((pc[:, 0] ** 2 + pc[:, 1] ** 2) / pc[:, 2] ** 2 >= _distortion_limit_r2(camera)):
        return None
    return uv


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
    uv = _projected_box_edges(lo, hi, camera, T)
    if uv is None:
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


def region_from_box(
    box_min: np.ndarray,
    box_max: np.ndarray,
    camera: CameraModel,
    T_base_camera: np.ndarray,
    margin_px: int = 10,
) -> np.ndarray | None:
    """Where a workspace box can appear in a view: the convex hull of its projected edges
    (with distortion, 9 points an edge), grown by ``margin_px``; ``(H, W)`` bool. None
    when part of the box lies behind the camera or beyond the radius where the lens
    model is monotonic (its image is unbounded); StageError when all of it lies behind
    the camera. :func:`roi_from_box` is its bounding rectangle; a box seen from above
    projects to a hexagon whose corners leave much of that rectangle to the table around
    the object."""
    lo, hi = _check_box(box_min, box_max)
    uv = _projected_box_edges(lo, hi, camera, np.asarray(T_base_camera, dtype=np.float64))
    if uv is None or not np.all(np.isfinite(uv)) or np.abs(uv).max() > 1e6:
        return None
    hull = cv2.convexHull(np.round(uv).astype(np.int32).reshape(-1, 1, 2))
    region = np.zeros((int(camera.height), int(camera.width)), np.uint8)
    cv2.fillConvexPoly(region, hull, 1)
    if margin_px > 0:
        k = 2 * int(margin_px) + 1
        region = cv2.dilate(region, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k)))
    return region.astype(bool)


# ---------------------------------------------------------------------- one view, a recording
def segment_view(
    image: np.ndarray,
    camera: CameraModel,
    T_base_camera: np.ndarray,
    workspace: tuple[np.ndarray, np.ndarray] | None = None,
    background: np.ndarray | None = None,
    *,
    options: SegmentOptions = SegmentOptions(),
) -> tuple[Silhouette, str]:
    """One view segmented as the pipeline does.

    The ROI is the projected workspace box when there is one (and
    ``options.roi_from_workspace``), else found automatically (``options.roi_auto``,
    :func:`find_roi`), else the image.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float in [0, 1]
    camera : CameraModel
    T_base_camera : (4, 4) float64
        The camera's pose in ``base``.
    workspace : ((3,), (3,)) float64, metres, in ``base``, optional
        The workspace box.
    background : array like ``image``, optional
        The empty scene at this pose.
    options : SegmentOptions
        Made from the config's ``segmentation`` section
        (``SegmentOptions.from_config(cfg["segmentation"])``).

    Returns
    -------
    silhouette : Silhouette
    roi_source : str
        ``"workspace box"``, ``"automatic"`` or ``"image"``.
    """
    roi, roi_source, region = None, "image", None
    if workspace is not None and options.roi_from_workspace:
        roi = roi_from_box(workspace[0], workspace[1], camera, T_base_camera,
                           margin_px=options.roi_margin_px)
        region = region_from_box(workspace[0], workspace[1], camera, T_base_camera,
                                 margin_px=options.roi_margin_px)
        roi_source = "workspace box"
    elif options.roi_auto:
        roi = find_roi(image, background=background, options=options)
        roi_source = "automatic"
    sil = segment_silhouette(image, roi=roi, background=background, options=options,
                             region=region)
    return sil, roi_source


#: The ``carving`` keys that :func:`resegment_spurious_views` reads (the silhouettes stage
#: re-runs when one of them changes, not when the carve's resolution or method does).
RESEGMENT_CARVING_KEYS = ("box_margin", "outside_image", "behind_camera", "qa_resolution",
                          "qa_max_missing", "qa_max_spurious", "qa_min_unexplained",
                          "qa_min_observers", "qa_leave_out")


#: The ``triangulation`` and ``alignment`` keys that the laser's check of the masks reads
#: (:func:`robo3d.artefacts.object_points`: the table, and the laser's box without one).
LASER_TRIANGULATION_KEYS = ("table_above_floor_mm", "table_max_tilt_deg", "workspace_margin_m")
LASER_ALIGNMENT_KEYS = ("workspace_from_hull_margin",)


def resegment_spurious_views(
    masks: list[np.ndarray],
    cameras: list[CameraModel],
    T_base_cameras: np.ndarray,
    workspace: tuple[np.ndarray, np.ndarray] | None,
    segment: Callable[[int, tuple[np.ndarray, np.ndarray]], np.ndarray | None],
    *,
    carving_cfg: Mapping[str, Any],
    exclude: Sequence[int] = (),
) -> tuple[dict[int, np.ndarray], dict[str, Any]]:
    """Segment again, inside the box of the other views' hull, the views whose foreground
    the other views rule out.

    A view segmented against its image border alone (no workspace box in the recording)
    takes whatever differs from that border as object: a turntable's plate seen whole
    from above, the table under a camera looking down. The other views, which saw the
    plate reach their border or end beside the object, carve it away. Each view is
    scored against the others' hull on the agreement check's coarse grid
    (:func:`robo3d.carving.flag_disagreeing_views`, the config's ``carving.qa_*``, the
    carving box as the carve places it, the grid ``qa_resolution`` whatever the carve's
    resolution). A view flagged because more than
    ``qa_max_spurious`` of its foreground lies outside that hull, and that misses no more
    than ``qa_max_missing`` of it, is segmented again by ``segment(view, box)`` with the
    box of the hull of the views not flagged (:func:`robo3d.carving.reference_box`, grown
    by ``carving.box_margin``; within the recording's box when there is one). A box
    restricts and cannot add, so a view flagged for missing part of the object is left
    to the carve's check. The new mask replaces the old one only when less of it lies
    outside the others' hull and it misses no more than the threshold.

    Parameters
    ----------
    masks, cameras, T_base_cameras
        The first segmentation's masks (empty where it failed) and the views' cameras and
        poses in ``base``.
    workspace : ((3,), (3,)) or None
        The recording's workspace box.
    segment : callable
        ``segment(view, (box_min, box_max))``: the view's mask segmented with that box
        as its workspace, or None when the segmentation failed.
    carving_cfg : mapping
        The config's ``carving`` section (the keys :data:`RESEGMENT_CARVING_KEYS`).
    exclude : sequence of int
        Views already suspect (the segmentation's own QA flags): not in the reference.

    Returns
    -------
    new_masks : dict
        View -> the mask that replaces its first one.
    report : dict
        ``checked`` (False with ``why_not`` when fewer than four views have a mask, the
        check is off, or no box can be placed), ``candidates`` (per flagged view:
        ``spurious_before`` / ``missing_before``, ``spurious_after`` / ``missing_after``,
        ``accepted``), ``box`` (the reference hull's box), ``time_s``.
    """
    import time

    from .carving import (
        AgreementOptions,
        CarveOptions,
        box_from_silhouettes,
        flag_disagreeing_views,
        reference_box,
        reference_suspects,
        view_agreement,
    )
    from .grid import make_grid

    t0 = time.perf_counter()
    agreement = AgreementOptions.from_config(carving_cfg)
    carve = CarveOptions(outside_image=carving_cfg["outside_image"],
                         behind_camera=carving_cfg["behind_camera"])
    report: dict[str, Any] = {"checked": False, "candidates": {}, "box": None}
    n = len(masks)
    with_mask = [i for i in range(n) if masks[i].any()]
    if agreement.qa_resolution == 0 or len(with_mask) < 4:
        report["why_not"] = ("carving.qa_resolution is 0" if agreement.qa_resolution == 0
                             else f"{len(with_mask)} views with a mask: too few")
        return {}, report
    if workspace is not None:
        lo, hi = workspace
    else:
        try:
            lo, hi, _ = box_from_silhouettes(None, [masks[i] for i in with_mask],
                                             [cameras[i] for i in with_mask],
                                             T_base_cameras[with_mask],
                                             margin=float(carving_cfg["box_margin"]))
        except StageError as exc:
            report["why_not"] = f"no carving box: {exc}"
            return {}, report
    grid = make_grid(lo, hi, resolution=agreement.qa_resolution)
    suspect = set(reference_suspects(masks, exclude)[0])
    qa = flag_disagreeing_views(grid, masks, cameras, T_base_cameras, options=agreement,
                                carve=carve, exclude=sorted(suspect))
    report["checked"] = True
    max_sp, max_mi = agreement.qa_max_spurious, agreement.qa_max_missing
    cand = [s for s in qa["views"] if s["flagged"] and s["spurious_fraction"] is not None
            and s["spurious_fraction"] > max_sp and s["missing_fraction"] is not None
            and s["missing_fraction"] <= max_mi]
    reference = [v for v in range(n) if v not in set(qa["flagged"]) | suspect]
    box = reference_box(grid, masks, cameras, T_base_cameras, reference,
                        margin=float(carving_cfg["box_margin"])) if cand else None
    if box is not None and workspace is not None:
        box = (np.maximum(box[0], workspace[0]), np.minimum(box[1], workspace[1]))
        box = box if np.all(box[1] > box[0]) else None
    report["box"] = None if box is None else [box[0].tolist(), box[1].tolist()]
    tried: dict[int, np.ndarray] = {}
    for s in cand if box is not None else ():
        m = segment(s["view"], box)
        if m is not None and m.any():
            tried[s["view"]] = m
    after = view_agreement(grid, [tried.get(i, masks[i]) for i in range(n)], cameras,
                           T_base_cameras, reference=reference, carve=carve,
                           min_observers=agreement.qa_min_observers) if tried else []
    new: dict[int, np.ndarray] = {}
    for s in cand:
        v = s["view"]
        a = after[v] if v in tried else {}
        ok = (a.get("spurious_fraction") is not None
              and a["spurious_fraction"] < s["spurious_fraction"]
              and a.get("missing_fraction") is not None and a["missing_fraction"] <= max_mi)
        report["candidates"][v] = {
            "spurious_before": s["spurious_fraction"], "missing_before": s["missing_fraction"],
            "spurious_after": a.get("spurious_fraction"),
            "missing_after": a.get("missing_fraction"), "accepted": bool(ok)}
        if ok:
            new[v] = tried[v]
    report["time_s"] = round(time.perf_counter() - t0, 3)
    return new, report


def score_recording_silhouettes(path: str, cfg: dict | None = None, *,
                                step: int = 1) -> dict:
    """Segment a recording's views with a config (default: the project's defaults) and
    score the masks against its ``ground_truth/silhouettes/NNN.png`` attachments.

    The segmentation from the views alone: the stage's test against the laser's points
    (:func:`resegment_laser_contradicted`) needs the triangulated clouds, so a scan whose
    views it re-segments scores better through the workflow (``metrics.json``'s
    ``evaluation.mask_iou``) than here.

    Parameters
    ----------
    path : str
        The recording.
    cfg : dict, optional
        A validated config (:func:`robo3d.config.load_config`); default config if None.
    step : int
        Score every ``step``-th view (1: all).

    Returns
    -------
    dict
        ``iou`` (per scored view, index -> IoU), ``iou_mean``, ``iou_min``,
        ``worst_view``, ``n_views``, ``n_scored``, ``seconds_per_view``, ``qa_flags``
        (index -> flags, only flagged views), ``failed`` (index -> why, the views whose
        segmentation failed: scored as an empty mask, as the stage leaves them).

    Raises
    ------
    robo3d.errors.StageError
        The recording has no ground-truth silhouettes.
    """
    import time

    from .config import load_config
    from .recording.reader import read_recording
    from .stages.common import reader_options

    cfg = load_config() if cfg is None else cfg
    rec = read_recording(path, roles=("views",), **reader_options(cfg))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    poses = rec.camera_poses(views)
    cameras = [rec.camera_for(m) for m in views]
    options = SegmentOptions.from_config(cfg["segmentation"])
    ious: dict[int, float] = {}
    flags: dict[int, list[str]] = {}
    seconds = 0.0
    scored = range(0, len(views), max(1, int(step)))
    images = {i: rec.decode(views[i]) for i in scored}
    sils: dict[int, Silhouette] = {}
    failed: dict[int, str] = {}
    for i in scored:
        t0 = time.perf_counter()
        try:
            sils[i] = segment_view(images[i], cameras[i], poses[i], rec.workspace,
                                   options=options)[0]
        except StageError as exc:  # as the stage does: an empty mask, the view flagged
            failed[i] = str(exc)
            sils[i] = Silhouette(np.zeros((cameras[i].height, cameras[i].width), bool),
                                 float("nan"), options.polarity, 0, 0, False,
                                 np.full(2, np.nan), (0, 0, 0, 0),
                                 qa={"flags": [f"segmentation failed: {exc}"]})
        seconds += time.perf_counter() - t0
    if step == 1 and cfg["segmentation"]["resegment_spurious"]:
        redone: dict[int, Silhouette] = {}

        def again(v: int, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
            try:
                redone[v] = segment_view(images[v], cameras[v], poses[v], box,
                                         options=options)[0]
            except StageError:  # the first mask stays, as in the stage
                return None
            return redone[v].mask

        t0 = time.perf_counter()
        new, _ = resegment_spurious_views(
            [sils[i].mask for i in scored], cameras, poses, rec.workspace, again,
            carving_cfg=cfg["carving"], exclude=[i for i in scored if sils[i].qa["flags"]])
        seconds += time.perf_counter() - t0
        sils.update({v: redone[v] for v in new})
    for i in scored:
        key = f"ground_truth/silhouettes/{i:03d}.png"
        if key not in rec.attachments:
            continue
        truth = cv2.imdecode(np.frombuffer(rec.attachments[key], np.uint8),
                             cv2.IMREAD_GRAYSCALE)
        rect = rec.rectifiers.get(views[i].frame_id)  # the view is segmented rectified
        if rect is not None and truth is not None and truth.shape == (rect.height, rect.width):
            truth = rect(truth)
        sil = sils[i]
        gt = truth > 127
        if gt.shape != sil.mask.shape:
            raise StageError(f"{path}: {key} is {gt.shape[1]}x{gt.shape[0]}, the view "
                             f"{sil.mask.shape[1]}x{sil.mask.shape[0]}")
        ious[i] = float(np.count_nonzero(gt & sil.mask) / max(np.count_nonzero(gt | sil.mask), 1))
        if sil.qa["flags"]:
            flags[i] = list(sil.qa["flags"])
    if not ious:
        raise StageError(f"{path}: no ground_truth/silhouettes/NNN.png attachments to score")
    vals = np.array(list(ious.values()))
    worst = min(ious, key=ious.get)
    return {"iou": ious, "iou_mean": float(vals.mean()), "iou_min": float(vals.min()),
            "worst_view": int(worst), "n_views": len(views), "n_scored": len(ious),
            "seconds_per_view": seconds / len(ious), "qa_flags": flags, "failed": failed}


def laser_pixels(points_base: np.ndarray, camera: CameraModel, T_base_camera: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The laser's points as they fall in a view: their pixels ``(M, 2)`` (int, rounded)
    and, ``(M,)``, the index of each point they come from (in front of the camera and
    inside the image; any point the laser measured on the object lies inside its
    silhouette in every view, whatever hides it from that view)."""
    uv, front = project_points(points_base, camera, T_base_camera)
    idx = np.flatnonzero(front & np.all(np.isfinite(uv), axis=1))
    px = np.rint(uv[idx]).astype(np.int64)
    inside = ((px[:, 0] >= 0) & (px[:, 0] < camera.width)
              & (px[:, 1] >= 0) & (px[:, 1] < camera.height))
    return px[inside], idx[inside]


def laser_outside_share(mask: np.ndarray, px: np.ndarray, tolerance_px: int) -> float:
    """The share of the laser's pixels ``px`` (from :func:`laser_pixels`) outside ``mask``
    grown by ``tolerance_px`` (the robot's error before the alignment moves the points by
    a pixel or two); NaN without pixels."""
    if len(px) == 0:
        return float("nan")
    m = np.asarray(mask, dtype=np.uint8)
    if tolerance_px > 0:
        m = cv2.dilate(m, cv2.getStructuringElement(
            cv2.MORPH_ELLIPSE, (2 * tolerance_px + 1, 2 * tolerance_px + 1)))
    return float(1.0 - np.count_nonzero(m[px[:, 1], px[:, 0]]) / len(px))


def laser_cover(px: np.ndarray, frames: np.ndarray, shape: tuple[int, int], *,
                max_radius_px: int = 15) -> tuple[np.ndarray, int]:
    """The region the laser's pixels cover in a view: the pixels closed
    (``cv2.MORPH_CLOSE``) with a disc that bridges the gap between neighbouring profiles.

    The gap is the median, over the pixels, of the distance to the nearest pixel of
    another laser frame (``frames``: each pixel's frame); the disc's radius half of it
    plus one, between 2 and ``max_radius_px``. Returns the cover ``(H, W)`` bool and the
    radius."""
    from scipy.spatial import cKDTree

    cover = np.zeros(shape, np.uint8)
    if len(px) == 0:
        return cover.astype(bool), 0
    cover[px[:, 1], px[:, 0]] = 1
    # one pixel per (pixel, frame): a profile is dense along itself, its neighbour across
    _, first = np.unique(px[:, 1] * shape[1] + px[:, 0] + frames.astype(np.int64)
                            * shape[0] * shape[1], return_index=True)
    p, f = px[first].astype(np.float64), np.asarray(frames)[first]
    radius = 2
    if len(p) > 1:
        k = min(16, len(p))
        d, i = cKDTree(p).query(p, k=k)
        other = f[i] != f[:, None]
        gap = np.where(other, d, np.inf).min(axis=1)
        gap = gap[np.isfinite(gap)]
        if len(gap):
            radius = int(np.clip(np.ceil(np.median(gap) / 2) + 1, 2, max_radius_px))
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))
    return cv2.morphologyEx(cover, cv2.MORPH_CLOSE, disc) > 0, radius


def resegment_laser_contradicted(
    masks: Sequence[np.ndarray],
    cameras: Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    points_base: np.ndarray,
    frames: np.ndarray,
    image: Callable[[int], np.ndarray],
    rois: Sequence[tuple[int, int, int, int] | None],
    *,
    max_outside: float = 0.2,
    tolerance_px: int = 2,
    min_points: int = 50,
    band_px: int = 6,
    min_area_ratio: float = 0.5,
) -> tuple[dict[int, np.ndarray], dict[str, Any]]:
    """Segment again, from where the laser measured the object, the views whose mask the
    laser contradicts.

    Every point the laser measured on the object lies inside the object's silhouette in
    every view. A view that leaves more than ``max_outside`` of those points outside its
    mask (grown by ``tolerance_px``: the robot's error before the alignment) took the
    object for background: a grey or white object on a grey table printed with dark
    markers (its dark stripes read as the markers' ink, its shaded side as the table), a
    black object, or a view whose segmentation failed outright. Such a view is segmented
    again by GrabCut (:func:`refine_with_grabcut`, undecided band ``band_px``) seeded
    with the region the laser covers in it (:func:`laser_cover`) instead of the colour
    model's mask, inside the view's region ``rois[v]``: the laser says where the object
    is, GrabCut's colour mixtures and image edges where its outline runs, up to
    ``band_px`` beyond the covered region (where the laser saw only part of the object
    from this view, the new mask stops there). The new mask replaces the old one when it
    leaves fewer of the points outside than before and no more than ``max_outside``, and
    is at least ``min_area_ratio`` of the old mask's area (or the old one was empty): the
    laser adds object where the mask missed it; a new mask far smaller than the old one
    is the laser measuring something else (a stripe read off a marker's edge beside a
    dark or weakly returning object), which the right mask leaves outside.

    Why: random scene 515 (a grey striped cup on a grey table printed with black dots,
    12 views) had masks of IoU 0.23-0.91 against the truth, mean 0.48, and 100 % of the
    laser's points outside them; seeded by the laser, 0.89-0.99, mean 0.96
    (``benchmarks/README.md``, stop 54). Good masks leave 0-3 % of the points outside
    (the robot's error, points at the object's foot). ``band_px`` 6 rather than GrabCut's
    usual 24: with a wider band the junk points of a laser the object barely returns
    (a blue laser on a red torus) took in the table around them; without the area test,
    four right masks (IoU 0.82-0.99) became 0.003-0.19.

    Parameters
    ----------
    masks, cameras, T_base_cameras
        The views' masks (empty where the segmentation failed), cameras and poses.
    points_base : (N, 3) float64
        The laser's points on the object (not the table, not outside the workspace), at
        the robot's poses, in ``base``.
    frames : (N,) int
        Each point's laser frame (its profile).
    image : callable
        ``image(view)``: the view's image, decoded.
    rois : sequence
        Per view the region it was segmented in ``(u0, v0, u1, v1)`` (None: the image).
    max_outside, tolerance_px, min_points, band_px, min_area_ratio
        See above; ``min_points``: fewer of the points in a view and it is not judged.

    Returns
    -------
    new_masks : dict
        View -> the mask that replaces its first one.
    report : dict
        ``points`` (how many), ``outside`` (per view: the share outside its mask, None
        when fewer than ``min_points`` fall in it), ``candidates`` (per contradicted view:
        ``outside_before``, ``outside_after``, ``area_ratio`` (new / old mask, None when
        the old was empty), ``radius_px`` of the cover, ``accepted``), ``time_s``.
    """
    import time

    t0 = time.perf_counter()
    report: dict[str, Any] = {"points": int(len(points_base)), "outside": [],
                              "candidates": {}}
    new: dict[int, np.ndarray] = {}
    frames = np.asarray(frames)
    for v, (mask, cam) in enumerate(zip(masks, cameras, strict=True)):
        px, idx = laser_pixels(points_base, cam, T_base_cameras[v])
        if len(px) < min_points:
            report["outside"].append(None)
            continue
        before = laser_outside_share(mask, px, tolerance_px)
        report["outside"].append(round(before, 4))
        if before <= max_outside:
            continue
        cover, radius = laser_cover(px, frames[idx], mask.shape)
        got = refine_with_grabcut(image(v), cover, rois[v], band_px=band_px)
        after = laser_outside_share(got, px, tolerance_px) if got.any() else 1.0
        ratio = float(np.count_nonzero(got)) / max(float(np.count_nonzero(mask)), 1.0)
        ok = after <= max_outside and after < before and (ratio >= min_area_ratio
                                                          or not mask.any())
        report["candidates"][v] = {"outside_before": round(before, 4),
                                   "outside_after": round(after, 4),
                                   "area_ratio": round(ratio, 3) if mask.any() else None,
                                   "radius_px": radius, "accepted": bool(ok)}
        if ok:
            new[v] = got
    report["time_s"] = round(time.perf_counter() - t0, 3)
    return new, report


def resegment_outside_box(
    masks: Sequence[np.ndarray],
    cameras: Sequence[CameraModel],
    T_base_cameras: np.ndarray,
    box: tuple[np.ndarray, np.ndarray],
    segment: Callable[[int], np.ndarray | None],
    *,
    max_outside: float = 0.1,
    margin_px: float = 10.0,
) -> tuple[dict[int, np.ndarray], dict[str, Any]]:
    """Segment again, with ``box`` as the workspace, the views whose mask lies more than
    ``max_outside`` outside the box's projection (:func:`region_from_box`, grown by
    ``margin_px``): in a recording without a workspace box, the box of the object that
    the laser measured (:func:`robo3d.artefacts.object_points`).

    Without a box each view is segmented against its image border; on a table printed
    with markers the border's sample can leave the table's plain parts as foreground, a
    mask five times the object in every view (random scene 528, an orange cup on a dots
    table: IoU 0.199-0.226), which no agreement between the views can catch (they agree)
    and no laser point contradicts (the object lies inside). ``segment(view)`` returns
    the view segmented inside ``box`` (None when that fails); the new mask replaces the
    old one when less of it lies outside the projection.

    Only a mask that touches the image border is a candidate (such a table runs out of
    the frame: 80-98 % of it on 524 and 528). A mask that ends inside the frame is an
    outline of its own, and the box is only what the laser measured of the object: one
    sweep over a cup measured a 2 x 4 cm sliver of it (random scene 542 of stop 55, the
    dark demo scene), and the cup's right masks, re-segmented inside that box, became the
    sliver (IoU 1.00 -> 0.04 in three of six views).

    Returns the new masks (view -> mask) and the report: ``outside`` (per view, the
    share of its mask outside the projection; None for an empty mask), ``candidates``
    (per view re-segmented: ``outside_before``, ``outside_after``, ``accepted``),
    ``inside_frame`` (the views beyond ``max_outside`` left as they are because their
    mask does not touch the image border).
    """
    report: dict[str, Any] = {"box": [np.asarray(box[0]).tolist(), np.asarray(box[1]).tolist()],
                              "outside": [], "candidates": {}, "inside_frame": []}
    new: dict[int, np.ndarray] = {}
    for v, (mask, cam) in enumerate(zip(masks, cameras, strict=True)):
        area = np.count_nonzero(mask)
        if area == 0:
            report["outside"].append(None)
            continue
        try:
            region = region_from_box(box[0], box[1], cam, T_base_cameras[v],
                                     margin_px=int(round(margin_px)))
        except StageError:  # the box behind the camera: nothing to test against
            region = None
        if region is None:
            report["outside"].append(None)
            continue
        before = 1.0 - np.count_nonzero(mask & region) / area
        report["outside"].append(round(float(before), 4))
        if before <= max_outside:
            continue
        if not silhouette_qa(mask, None)["sides_touched"]:  # of the image itself
            report["inside_frame"].append(v)
            continue
        got = segment(v)
        after = (1.0 - np.count_nonzero(got & region) / max(np.count_nonzero(got), 1)
                 if got is not None and got.any() else None)
        ok = after is not None and after < before
        report["candidates"][v] = {"outside_before": round(float(before), 4),
                                   "outside_after": None if after is None
                                   else round(float(after), 4), "accepted": bool(ok)}
        if ok:
            new[v] = got
    return new, report
