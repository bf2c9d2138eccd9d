"""Laser stripe detection: one sub-pixel stripe centre per image column (or row).

Implements the seed's §4.2 ("Detection of the laser path") and finishes its last step,
"associate a line to the band", with a sub-pixel peak estimator.

The method, per frame
---------------------
1. Lightness ``L`` (seed eq. 19): ``L = (max(R, G, B) + min(R, G, B)) / 2``; a mono image
   is its own lightness (R = G = B). When a laser-off ``background`` frame is given, the
   frame is first replaced by ``max(image - background, 0)`` channel by channel.
2. Brightness coefficient ``s`` (seed eq. 18), the mid-range of the mean R, G, B of samples
   on the laser line. The seed lets a user click the samples; we take them automatically:
   the ``top_fraction`` brightest pixels (by ``L``) of the frame, or of the laser-on minus
   laser-off difference when a background is given. A caller may still pass its own
   samples (mask or pixel list), or ``s`` itself.
3. Band mask ``I_b`` (seed eq. 20): ``(1 - band) s <= L <= (1 + band) s`` (``band = 0.15``
   in the seed). The band only *locates* the stripe in each line (column or row):
   a *blob* is a contiguous run of ``L >= (1 - band) s`` along the line. A blob holding
   at least one band pixel is the stripe; a blob brighter than the band everywhere
   (it steps over the band between two pixels) is ignored when a band blob shares its
   line — a white highlight beside the laser, which is what the band's upper bound is
   for — and taken as the stripe when it is alone in its line: a stripe brighter than
   ``(1 + band) s`` is still a stripe, and on a sampled profile its flanks may jump
   over a ±15 % band. A line with two or more band blobs (or, without any, two or more
   bright blobs) is ambiguous, a reflection of the sheet: rejected. A line where
   nothing reaches the band's lower edge has no stripe.
4. Sub-pixel centre ("associate a line to the band"). Around the candidate blob's
   brightest pixel ``p`` a window of ``±h`` pixels (``h`` from ``max_width_px``) is read.
   The local background ``b`` is the minimum of the window's 3-pixel running mean, so a
   bright feature on one side of the stripe does not raise it. With ``y = L - b``,
   amplitude ``A = y(p)`` and a tail threshold ``T = max(tail_fraction * A,
   noise_k * sigma_noise)``, the centre is the centre of gravity of the soft-thresholded
   profile ``max(y - T, 0)`` over the contiguous run around ``p`` where ``y > T``. The
   weights fall continuously to zero at the run's ends, so the estimate stays unbiased
   (below 0.01 px on a sampled Gaussian) even where the band clipped the peak — the band
   is never used as the weight, only to find the run. ``method="gaussian"`` instead fits
   a parabola to ``ln y`` over the same run by least squares with weights ``y²``
   (Guo 2011): the 3-point Gaussian estimator when the run is three pixels long,
   exact for a noise-free Gaussian profile, and less noisy than the 3-point form on
   wide stripes; it falls back to the centre of gravity where the fit is not defined
   (fewer than three pixels, a flat saturated top, a vertex off the peak pixel).
5. Rejections, each line counted once, by reason: ``too_weak`` (``A`` below
   ``min_peak``), ``too_wide`` (full width at half maximum above ``max_width_px``, or the
   run filling the window), ``at_border`` (the run is cut by the image border, the centre
   would be biased).
6. Confidence in [0, 1]: the product of an SNR term ``1 - exp(-A / (10 sigma_noise))``,
   a width term (1 up to half of ``max_width_px``, falling linearly to 0 at it) and a
   contrast term ``min(1, A / ((1 - band) s))``. ``sigma_noise`` is the frame's noise,
   estimated robustly from the median absolute difference of neighbouring pixels along
   the lines (Donoho's MAD estimator on first differences).

Everything is vectorised over all lines of the frame at once; the only loop is over the
frames of a batch.

Choices where the seed is vague
-------------------------------
* The seed's image is RGB and the laser red; we accept any laser colour (eq. 19 is
  colour-blind) and mono images.
* Images are read in their own units (grey levels for integer images); ``min_peak`` is
  in those units (the config's ``stripes.min_peak`` is in grey levels), and defaults to
  4 % of the full scale (255 for uint8, 65535 for uint16, 1.0 for float images).
* The stripe of our rig runs roughly horizontally (the laser sits along camera -y and
  its sheet spans camera x), so the default ``axis="columns"`` gives one centre per
  column: ``u`` is the (integer) column and ``v`` the sub-pixel row. ``axis="rows"``
  gives one centre per row; ``axis="auto"`` picks the stripe's dominant direction from
  the principal axis of the band pixels.

References
----------
.. [1] The seed chapter, "Robot assisted 3D shape acquisition by optical systems", §4.2,
   eqs. 18–20.
.. [2] R. B. Fisher and D. K. Naidu, "A comparison of algorithms for subpixel peak
   detection", in Image Technology, Springer, 1996 (centre of gravity, Gaussian
   3-point fit).
.. [3] H. Guo, "A simple algorithm for fitting a Gaussian function", IEEE Signal
   Processing Magazine 28(5), 2011.
.. [4] C. Steger, "An unbiased detector of curvilinear structures", IEEE TPAMI 20(2),
   1998.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

__all__ = [
    "StripePoints",
    "REJECTION_REASONS",
    "brightness_coefficient",
    "lightness",
    "extract_stripe_centres",
    "extract_stripes_batch",
]

log = logging.getLogger(__name__)

#: Reasons a line (column or row) yields no centre, as counted in
#: :attr:`StripePoints.rejected`.
REJECTION_REASONS: tuple[str, ...] = (
    "no_band",
    "two_blobs",
    "too_weak",
    "too_wide",
    "at_border",
)

_Axis = Literal["columns", "rows", "auto"]


@dataclass
class StripePoints:
    """The stripe centres found in one frame, one per image line at most.

    Attributes
    ----------
    u, v : (N,) float64, pixels
        Sub-pixel stripe centres (column, row), origin at the centre of the top-left
        pixel. With ``axis="columns"`` ``u`` is the integer column and ``v`` sub-pixel.
    confidence : (N,) float64 in [0, 1]
        Heuristic quality of each centre (SNR, width, contrast); ones when not given.
    peak : (N,) float64
        Peak height above the local background, in lightness units of the image.
    width_px : (N,) float64, pixels
        Full width at half maximum of the stripe across the line.
    line : (N,) int64
        Index of the line each centre belongs to: the column for ``axis="columns"``,
        the row for ``axis="rows"``. Defaults to the rounded ``u`` (or ``v``).
    axis : str
        ``"columns"`` or ``"rows"``: the direction the centres were searched in. When
        not given (None), inferred from the centres: ``"rows"`` if every ``v`` is an
        integer and some ``u`` is not, else ``"columns"`` — so a frame rebuilt from
        stored ``u, v`` keeps its lines.
    s : float
        The brightness coefficient (seed eq. 18) used.
    n_lines : int
        Number of lines examined.
    rejected : dict of str to int
        Lines that gave no centre, by reason (keys :data:`REJECTION_REASONS`).
    """

    u: np.ndarray
    v: np.ndarray
    confidence: np.ndarray | None = None
    peak: np.ndarray | None = None
    width_px: np.ndarray | None = None
    line: np.ndarray | None = None
    axis: str | None = None
    s: float = float("nan")
    n_lines: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECTION_REASONS, 0))

    def __post_init__(self) -> None:
        self.u = np.asarray(self.u, dtype=np.float64).reshape(-1)
        self.v = np.asarray(self.v, dtype=np.float64).reshape(-1)
        n = self.u.size
        if self.v.size != n:
            raise ValueError(f"u and v must have the same length, got {n} and {self.v.size}")
        if self.axis is None:
            int_u = bool(np.all(self.u == np.rint(self.u)))
            int_v = bool(np.all(self.v == np.rint(self.v)))
            self.axis = "rows" if (int_v and not int_u) else "columns"
        if self.axis not in ("columns", "rows"):
            raise ValueError(f"axis must be 'columns' or 'rows', got {self.axis!r}")

        def _vec(x: np.ndarray | None, default: float, name: str) -> np.ndarray:
            if x is None:
                return np.full(n, default, dtype=np.float64)
            x = np.asarray(x, dtype=np.float64).reshape(-1)
            if x.size != n:
                raise ValueError(f"{name} must have {n} entries like u, got {x.size}")
            return x

        self.confidence = _vec(self.confidence, 1.0, "confidence")
        self.peak = _vec(self.peak, np.nan, "peak")
        self.width_px = _vec(self.width_px, np.nan, "width_px")
        if self.line is None:
            along = self.u if self.axis == "columns" else self.v
            self.line = np.rint(along).astype(np.int64) if n else np.zeros(0, np.int64)
        else:
            self.line = np.asarray(self.line, dtype=np.int64).reshape(-1)
            if self.line.size != n:
                raise ValueError(f"line must have {n} entries like u, got {self.line.size}")
        full = dict.fromkeys(REJECTION_REASONS, 0)
        full.update({k: int(c) for k, c in self.rejected.items()})
        self.rejected = full

    def __len__(self) -> int:
        return int(self.u.size)

    @property
    def pixels_uv(self) -> np.ndarray:
        """The centres as ``(N, 2)`` float64 ``(u, v)`` pixels."""
        return np.stack([self.u, self.v], axis=-1)

    @classmethod
    def empty(cls, *, axis: str = "columns", s: float = float("nan"), n_lines: int = 0,
              rejected: dict[str, int] | None = None) -> StripePoints:
        """A frame without any centre."""
        z = np.zeros(0)
        return cls(z, z, axis=axis, s=s, n_lines=n_lines,
                   rejected=dict(rejected or {}))


# ---------------------------------------------------------------------------- helpers
def _check_image(image: np.ndarray, name: str = "image") -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(image).__name__}")
    ok_shape = image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
    if not ok_shape:
        raise ValueError(f"{name} must be (H, W) mono or (H, W, 3) RGB, got shape "
                         f"{image.shape} {image.dtype}")
    if image.dtype == np.bool_ or not (np.issubdtype(image.dtype, np.integer)
                                       or np.issubdtype(image.dtype, np.floating)):
        raise ValueError(f"{name} must be an integer or float image, got {image.dtype}")
    return image


def _full_scale(dtype: np.dtype) -> float:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return 1.0


def _subtract_background(image: np.ndarray, background: np.ndarray | None) -> np.ndarray:
    """``max(image - background, 0)`` as float32 (or the image itself when no background)."""
    if background is None:
        return image
    background = _check_image(np.asarray(background), "background")
    if background.shape != image.shape:
        raise ValueError(f"background must have the image's shape {image.shape}, got "
                         f"{background.shape}")
    diff = image.astype(np.float32) - background.astype(np.float32)
    np.maximum(diff, 0.0, out=diff)
    return diff


def lightness(image: np.ndarray) -> np.ndarray:
    """Lightness of an image, seed eq. 19: ``L = (max(R, G, B) + min(R, G, B)) / 2``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        Mono or RGB image (channel order does not matter: eq. 19 is symmetric).

    Returns
    -------
    (H, W) float32
        Lightness in the image's own units; a mono image is returned as float32.

    References
    ----------
    .. [1] The seed chapter, §4.2, eq. 19 (the HSL lightness).
    """
    image = _check_image(np.asarray(image))
    if image.ndim == 2:
        return image.astype(np.float32)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    # channel-wise maximum/minimum: much faster than reducing over the last axis
    out = np.maximum(np.maximum(r, g), b).astype(np.float32)
    out += np.minimum(np.minimum(r, g), b)
    out *= 0.5
    return out


def _sample_mask(sample: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    sample = np.asarray(sample)
    if sample.dtype == np.bool_:
        if sample.shape != shape:
            raise ValueError(f"sample mask must be (H, W) = {shape} bool, got {sample.shape}")
        return sample
    if sample.ndim != 2 or sample.shape[1] != 2:
        raise ValueError(f"sample must be an (H, W) bool mask or (N, 2) pixels (u, v), got "
                         f"shape {sample.shape} {sample.dtype}")
    uv = np.rint(np.asarray(sample, dtype=np.float64)).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[0])
    if not np.all(inside):
        bad = uv[~inside][0]
        raise ValueError(f"sample pixel (u, v) = ({bad[0]}, {bad[1]}) is outside the "
                         f"{shape[1]}x{shape[0]} image")
    mask = np.zeros(shape, dtype=bool)
    mask[uv[:, 1], uv[:, 0]] = True
    return mask


def _brightness(image: np.ndarray, L: np.ndarray, sample: np.ndarray | None,
                top_fraction: float) -> float:
    h, w = L.shape
    if h * w == 0:
        return 0.0
    if sample is not None:
        mask = _sample_mask(sample, (h, w))
        if not mask.any():
            raise ValueError("sample selects no pixel")
    else:
        if not (0.0 < top_fraction <= 1.0):
            raise ValueError(f"top_fraction must be in (0, 1], got {top_fraction}")
        n = max(1, int(round(top_fraction * h * w)))
        flat = L.reshape(-1)
        thr = np.partition(flat, flat.size - n)[flat.size - n]
        mask = L >= thr
    if image.ndim == 2:
        means = np.array([float(image[mask].astype(np.float64).mean())])
    else:
        means = image[mask].astype(np.float64).mean(axis=0)
    return float((means.max() + means.min()) / 2.0)


def brightness_coefficient(
    image: np.ndarray,
    *,
    sample: np.ndarray | None = None,
    top_fraction: float = 0.002,
    background: np.ndarray | None = None,
) -> float:
    """Brightness coefficient ``s`` of the laser line, seed eq. 18.

    ``s = (max(mean R, mean G, mean B) + min(mean R, mean G, mean B)) / 2`` over samples
    of the laser line. The seed's user clicks the samples; by default we take the
    ``top_fraction`` brightest pixels of the frame by lightness (eq. 19), or of the
    laser-on minus laser-off difference when ``background`` is given.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        The laser-lit frame (mono: R = G = B).
    sample : (H, W) bool or (N, 2) float, optional
        The samples: a mask, or pixels ``(u, v)`` (rounded to the nearest pixel).
    top_fraction : float
        Fraction of the frame's pixels taken as samples when ``sample`` is None
        (at least one pixel).
    background : same shape as ``image``, optional
        A laser-off frame; the samples and the means are taken on
        ``max(image - background, 0)``.

    Returns
    -------
    float
        ``s`` in the image's units (0.0 for an image without pixels).

    References
    ----------
    .. [1] The seed chapter, §4.2, eq. 18.
    """
    image = _check_image(np.asarray(image))
    image = _subtract_background(image, background)
    return _brightness(image, lightness(image), sample, top_fraction)


def _noise_sigma(A: np.ndarray) -> float:
    """Robust noise of a (P, Q) profile stack: MAD of first differences along axis 0."""
    if A.shape[0] < 2 or A.shape[1] == 0:
        return 0.0
    step = max(1, A.shape[1] // 256)  # a few hundred lines are plenty
    d = np.abs(np.diff(A[:, ::step], axis=0))
    return float(1.4826 * np.median(d) / np.sqrt(2.0))


def _dominant_axis(in_band: np.ndarray) -> str:
    """'columns' when the band pixels spread more along u than along v."""
    rows, cols = np.nonzero(in_band)
    if rows.size < 2:
        return "columns"
    cov = np.cov(np.stack([cols, rows]).astype(np.float64))
    evals, evecs = np.linalg.eigh(cov)
    main = evecs[:, -1]
    return "columns" if abs(main[0]) >= abs(main[1]) else "rows"


def _run_along(mask: np.ndarray) -> np.ndarray:
    """Length of the run of True from the first entry on, along axis 0 (contiguous)."""
    return np.logical_and.accumulate(mask, axis=0).sum(axis=0)


# ---------------------------------------------------------------------------- extraction
def extract_stripe_centres(
    image: np.ndarray,
    *,
    band: float = 0.15,
    s: float | None = None,
    axis: _Axis = "columns",
    min_peak: float | None = None,
    max_width_px: float = 15.0,
    method: Literal["cog", "gaussian"] = "cog",
    background: np.ndarray | None = None,
    top_fraction: float = 0.002,
    tail_fraction: float = 0.05,
    noise_k: float = 3.0,
) -> StripePoints:
    """Sub-pixel laser stripe centres, at most one per image column (or row).

    See the module docstring for the method (seed §4.2, eqs. 18–20, then a centre of
    gravity or a Gaussian 3-point fit per line).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        The laser-lit frame, mono or RGB, any laser colour.
    band : float
        Half-width of the brightness band of eq. 20 relative to ``s`` (0.15 in the seed).
    s : float, optional
        Brightness coefficient; computed by :func:`brightness_coefficient` when None.
    axis : {"columns", "rows", "auto"}
        One centre per column (stripe roughly horizontal), per row, or chosen from the
        band pixels' dominant direction.
    min_peak : float, optional
        Smallest accepted peak height above the local background, in the image's units
        (grey levels for integer images). Default: 4 % of the full scale (10.2 for
        uint8, 2621.4 for uint16, 0.04 for float images).
    max_width_px : float, pixels
        Largest accepted full width at half maximum across the line.
    method : {"cog", "gaussian"}
        Centre of gravity of the background-subtracted, soft-thresholded run, or the
        Gaussian (weighted log-parabola) fit over the same run.
    background : same shape as ``image``, optional
        Laser-off frame subtracted (clipped at 0) before anything else.
    top_fraction : float
        Passed to :func:`brightness_coefficient` when ``s`` is None.
    tail_fraction : float
        Soft threshold of the centre of gravity, relative to the peak height.
    noise_k : float
        The soft threshold is at least ``noise_k`` times the frame's noise sigma.

    Returns
    -------
    StripePoints
        The centres, their confidence, peak and width, and the rejected lines by reason.
        A frame without a stripe (a black frame, an empty array) gives zero centres,
        not an error.

    References
    ----------
    .. [1] The seed chapter, §4.2, eqs. 18–20.
    .. [2] R. B. Fisher and D. K. Naidu, "A comparison of algorithms for subpixel peak
       detection", 1996.
    """
    image = _check_image(np.asarray(image))
    if axis not in ("columns", "rows", "auto"):
        raise ValueError(f"axis must be 'columns', 'rows' or 'auto', got {axis!r}")
    if method not in ("cog", "gaussian"):
        raise ValueError(f"method must be 'cog' or 'gaussian', got {method!r}")
    if not (0.0 < band < 1.0):
        raise ValueError(f"band must be in (0, 1), got {band}")
    if not (max_width_px > 0):
        raise ValueError(f"max_width_px must be positive, got {max_width_px}")
    if min_peak is not None and not (min_peak >= 0):
        raise ValueError(f"min_peak must be >= 0, got {min_peak}")
    if not (0.0 <= tail_fraction < 1.0) or not (noise_k >= 0):
        raise ValueError(f"need 0 <= tail_fraction < 1 and noise_k >= 0, got "
                         f"{tail_fraction} and {noise_k}")
    full_scale = _full_scale(image.dtype)
    work = _subtract_background(image, background)
    L = lightness(work)
    h_img, w_img = L.shape
    if s is None:
        s = _brightness(work, L, None, top_fraction)
    s = float(s)
    lo, hi = (1.0 - band) * s, (1.0 + band) * s
    min_peak_abs = 0.04 * full_scale if min_peak is None else float(min_peak)

    if L.size == 0:
        ax = "columns" if axis == "auto" else axis
        return StripePoints.empty(axis=ax, s=s, n_lines=w_img if ax == "columns" else h_img)

    in_band_img = None
    if axis == "auto":
        in_band_img = (L >= lo) & (L <= hi)
        axis = _dominant_axis(in_band_img) if s > min_peak_abs else "columns"
    A = L if axis == "columns" else L.T  # (P, Q): profiles along axis 0, one per line
    P, Q = A.shape
    rejected = dict.fromkeys(REJECTION_REASONS, 0)

    if not np.isfinite(s) or s <= min_peak_abs:
        # nothing in the frame is bright enough to be a stripe
        rejected["too_weak"] = Q
        log.debug("no stripe: brightness coefficient s=%.4g below min_peak %.4g", s,
                  min_peak_abs)
        return StripePoints.empty(axis=axis, s=s, n_lines=Q, rejected=rejected)

    # --- locate: blobs = runs of L >= lo; the eq. 20 band picks the stripe's blob
    above = A >= lo
    if in_band_img is not None:
        in_band = in_band_img if axis == "columns" else in_band_img.T
    else:
        in_band = above & (A <= hi)
    starts = above.copy()
    starts[1:] &= ~above[:-1]
    run_id = np.cumsum(starts, axis=0, dtype=np.int32)
    big = np.iinfo(np.int32).max
    rid_max = np.where(in_band, run_id, 0).max(axis=0)
    rid_min = np.where(in_band, run_id, big).min(axis=0)
    n_runs = run_id[-1]  # runs of L >= lo in each line
    has_band = rid_max > 0
    # a line whose only run steps over the band (brighter than (1 + band) s everywhere)
    # is a stripe brighter than the band; beside a band run, such a run is ignored
    bright_only = ~has_band & (n_runs == 1)
    two = (has_band & (rid_min != rid_max)) | (~has_band & (n_runs > 1))
    rid = np.where(has_band, rid_max, 1)
    rejected["no_band"] = int((n_runs == 0).sum())
    rejected["two_blobs"] = int(two.sum())
    lines = np.flatnonzero((has_band | bright_only) & ~two)
    if lines.size == 0:
        return StripePoints.empty(axis=axis, s=s, n_lines=Q, rejected=rejected)

    Ac = A[:, lines]
    blob = above[:, lines] & (run_id[:, lines] == rid[lines][None, :])
    p = np.argmax(np.where(blob, Ac, -np.inf), axis=0)  # brightest pixel of the blob

    # --- window of +-h around the peak
    h = int(np.ceil(1.1 * max_width_px)) + 2
    k = np.arange(-h, h + 1)
    rows = p[None, :] + k[:, None]
    valid = (rows >= 0) & (rows < P)
    Y = np.take_along_axis(Ac, np.clip(rows, 0, P - 1), axis=0).astype(np.float64)
    Y[~valid] = np.nan
    Yinf = np.where(valid, Y, np.inf)
    box = (Yinf[:-2] + Yinf[1:-1] + Yinf[2:]) / 3.0
    bg = box.min(axis=0)
    bg = np.where(np.isfinite(bg), bg, np.nanmin(Y, axis=0))
    y = Y - bg[None, :]
    amp = y[h]

    sigma_n = _noise_sigma(A)
    T = np.maximum(tail_fraction * amp, noise_k * sigma_n)
    wt = y - T[None, :]  # NaN outside the image: comparisons are False
    right = wt[h + 1:] > 0
    left = wt[h - 1::-1] > 0
    nr = _run_along(right)
    nl = _run_along(left)
    # the pixel that stopped each run: outside the image means the run was cut there
    cols = np.arange(lines.size)
    stop_r = np.minimum(h + 1 + nr, 2 * h)
    stop_l = np.maximum(h - 1 - nl, 0)
    cut = ((nr < h) & ~valid[stop_r, cols]) | ((nl < h) & ~valid[stop_l, cols])
    filled = (nr >= h) | (nl >= h)

    support = np.zeros_like(right, shape=y.shape)
    support[h] = True
    support[h + 1:] = np.logical_and.accumulate(right, axis=0)
    support[h - 1::-1] = np.logical_and.accumulate(left, axis=0)
    weights = np.where(support, np.maximum(wt, 0.0), 0.0)
    wsum = weights.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        offset = (weights * k[:, None]).sum(axis=0) / wsum

    if method == "gaussian":
        # weighted least-squares parabola through ln y over the run, weights y^2
        # (Guo 2011); with the run reduced to p-1, p, p+1 it is the classical 3-point
        # Gaussian estimator, and it is exact for a noise-free Gaussian either way.
        gw = np.where(support & (y > 0), y, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            ly = np.where(gw > 0, np.log(np.where(gw > 0, gw, 1.0)), 0.0)
        gw = gw * gw
        kk = k[:, None].astype(np.float64)
        m = [(gw * kk**i).sum(axis=0) for i in range(5)]
        rhs = np.stack([(gw * ly * kk**i).sum(axis=0) for i in range(3)], axis=-1)
        M = np.stack([np.stack([m[0], m[1], m[2]], -1), np.stack([m[1], m[2], m[3]], -1),
                      np.stack([m[2], m[3], m[4]], -1)], axis=-2)
        det = np.linalg.det(M)
        solvable = (support.sum(axis=0) >= 3) & (np.abs(det) > 1e-12 * np.abs(m[0]) ** 3)
        coef = np.zeros((lines.size, 3))
        if solvable.any():
            coef[solvable] = np.linalg.solve(M[solvable], rhs[solvable][..., None])[..., 0]
        b1, c2 = coef[:, 1], coef[:, 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            og = -b1 / (2.0 * c2)
        ok = solvable & (c2 < 0) & (np.abs(og) <= 1.5)
        offset = np.where(ok, og, offset)

    # full width at half maximum, linearly interpolated at both crossings
    half = amp / 2.0
    rr = y[h + 1:] >= half[None, :]
    ll = y[h - 1::-1] >= half[None, :]
    mr = _run_along(rr)
    ml = _run_along(ll)

    def _edge(m: np.ndarray, side: np.ndarray) -> np.ndarray:
        # side: (h, N) samples outward from the peak; crossing after m samples above half
        inside = np.where(m > 0, side[np.maximum(m - 1, 0), cols], amp)
        outside = side[np.minimum(m, h - 1), cols]
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = (inside - half) / (inside - outside)
        frac = np.where(np.isfinite(frac) & (m < h), np.clip(frac, 0.0, 1.0), 0.5)
        return m + frac

    width = _edge(mr, y[h + 1:]) + _edge(ml, y[h - 1::-1])

    too_weak = ~(amp >= min_peak_abs) | ~(wt[h] > 0)
    too_wide = ~too_weak & (filled | (width > max_width_px))
    at_border = ~too_weak & ~too_wide & cut
    rejected["too_weak"] = int(too_weak.sum())
    rejected["too_wide"] = int(too_wide.sum())
    rejected["at_border"] = int(at_border.sum())
    good = ~(too_weak | too_wide | at_border) & np.isfinite(offset)

    centre = p[good] + offset[good]
    amp_g, width_g = amp[good], width[good]
    c_snr = 1.0 - np.exp(-amp_g / (10.0 * max(sigma_n, 1e-12)))
    c_width = np.clip(2.0 - 2.0 * width_g / max_width_px, 0.0, 1.0)
    c_peak = np.clip(amp_g / lo, 0.0, 1.0)
    conf = np.clip(c_snr * c_width * c_peak, 0.0, 1.0)

    line_idx = lines[good].astype(np.int64)
    if axis == "columns":
        u, v = line_idx.astype(np.float64), centre
    else:
        u, v = centre, line_idx.astype(np.float64)
    return StripePoints(u=u, v=v, confidence=conf, peak=amp_g, width_px=width_g,
                        line=line_idx, axis=axis, s=s, n_lines=Q, rejected=rejected)


def extract_stripes_batch(
    frames: np.ndarray | Sequence[np.ndarray], **kw: object
) -> list[StripePoints]:
    """:func:`extract_stripe_centres` on every frame of a batch.

    Parameters
    ----------
    frames : (F, H, W) or (F, H, W, 3) array, or a sequence of (H, W[, 3]) arrays
        The laser-lit frames.
    **kw
        Keyword arguments of :func:`extract_stripe_centres` (``s`` applies to every
        frame; when None each frame gets its own brightness coefficient).

    Returns
    -------
    list of StripePoints
        One per frame, in order.
    """
    if isinstance(frames, np.ndarray):
        if frames.ndim not in (3, 4) or (frames.ndim == 3 and frames.shape[2] == 3):
            raise ValueError(f"frames must be (F, H, W) or (F, H, W, 3) (a single RGB "
                             f"image is not a batch), got shape {frames.shape}")
    return [extract_stripe_centres(f, **kw) for f in frames]  # type: ignore[arg-type]
