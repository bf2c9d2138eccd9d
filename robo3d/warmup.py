"""Compile the pipeline's numba kernels into numba's on-disk cache, once.

A fresh install (or an edit of a module) has no compiled kernels: the first process that
calls one compiles it (the stripe detector's kernels for 8-bit frames: about 35 s of CPU
on a 2-core Intel Xeon, 100 s before its helpers were compiled as functions of their own
instead of inlined into every kernel, stop 55; the carver's: about 6 s) and writes it to the cache
(``robo3d/__pycache__``), which later processes load in well under a second. Processes
that start side by side before the cache is written each compile it themselves: a batch
of N recordings on N cores (or N SLURM jobs) pays the compilation N times over, and on a
2-core machine the test suite's end-to-end runs (seven stripe jobs at once) paid about
two minutes for it. ``robo3d warm-up`` compiles them once, the detector, the carver and
the geometry (triangulation, silhouette term) in two processes side by side, before such
a batch starts (``./run.sh`` does it before the demo and before the tests). Nothing it
computes is kept; what the kernels compute is the same either way. It calls each in the
ways its stage does (a kernel is compiled once per argument types):
``tests/test_warmup.py`` checks that the stages' calls then compile nothing.

Only the image types a recording's laser frames decode to (8-bit RGB and mono) are
compiled by default; other types (16-bit, float) and the other detector and centre
methods compile at their first use, or with ``robo3d warm-up --all-types`` (about 60 s
of CPU more: the 16-bit and float frames beside the 8-bit detector, the other methods
after it; ``./run.sh test`` uses it, as the stripe tests call every type. Measured on a
2-core Intel Xeon with a cold cache, stop 55: 43 s without it, 56 s with it; 106 s and
137 s with the helpers inlined).
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor
from functools import partial
from itertools import product

import numpy as np

__all__ = ["compile_kernels", "tiny_stripe_frame"]


def tiny_stripe_frame() -> np.ndarray:
    """A 48 x 64 8-bit mono frame with one slightly tilted Gaussian stripe (peak 200): the
    smallest input that takes the detector through its kernels."""
    yy, xx = np.mgrid[0:48, 0:64]
    return np.clip(np.rint(200.0 * np.exp(-0.5 * ((yy - 20.0 - 0.1 * xx) / 1.5) ** 2)), 0,
                   255).astype(np.uint8)


def _red_frame(mono: np.ndarray) -> np.ndarray:
    """``mono`` as the red channel of an RGB frame on a dark grey scene (a red laser)."""
    return np.stack([mono, np.full_like(mono, 10), np.full_like(mono, 10)], axis=-1)


def _stripes() -> float:
    """The stripe detector on tiny 8-bit RGB and mono frames, the line both ways, in the
    ways the stripes stage calls it: the laser's colour estimated, then each frame with
    that colour fixed, the axis free or fixed by the laser's geometry, with and without
    the workspace's region of interest, the centre on the laser's channel or the luma.
    Numba compiles a kernel once per argument types, and these paths pass other types
    (the region's spans) or reach other kernels: warmed with the defaults only, the
    stage compiled 12 more on its first monochrome cell recording (36 s of its first
    frame on 2 cores)."""
    from .stripes import StripeOptions, estimate_laser_colour, extract_stripe_centres

    t0 = time.perf_counter()
    mono = tiny_stripe_frame()
    rgb = _red_frame(mono)
    for img, colour in ((rgb, "red"), (mono, "lightness")):
        for im in (img, np.ascontiguousarray(np.swapaxes(img, 0, 1))):
            roi = np.zeros(im.shape[:2], dtype=bool)
            roi[2:-2, 2:-2] = True
            estimate_laser_colour([im], min_peak=5.0)
            estimate_laser_colour([im], min_peak=5.0, rois=[roi], axes=["columns"])
            centres = ("laser", "luma") if im.ndim == 3 else ("laser",)
            for col, axis, centre_on, r in product(("auto", colour), ("auto", "columns", "rows"),
                                                   centres, (None, roi)):
                extract_stripe_centres(im, roi=r, options=StripeOptions(
                    min_peak=5.0, colour=col, axis=axis, centre_on=centre_on))
    return time.perf_counter() - t0


def _other_frames(deep: bool) -> list[tuple[np.ndarray, float]]:
    """The frames the default warm-up leaves out, with their ``min_peak``: 16-bit and
    float, mono and RGB (``deep``), or 8-bit RGB, grey RGB and mono (for the other
    methods)."""
    u8 = tiny_stripe_frame()
    rgb8 = _red_frame(u8)
    if deep:
        return [(u8.astype(np.float32) / 255.0, 0.04), (u8.astype(np.uint16) * 257, 2570.0),
                (rgb8.astype(np.float32) / 255.0, 0.02), (rgb8.astype(np.uint16) * 257, 1285.0)]
    return [(rgb8, 5.0), (np.repeat(u8[..., None], 3, axis=2), 5.0), (u8, 5.0)]


def _stripes_other(deep: bool) -> float:
    """The detector on the frames of :func:`_other_frames` with each detector and centre
    method (on 8-bit frames all but the default's, :func:`_stripes`), each the line both
    ways and the axis free or fixed; and a colour curve followed where it fades
    (``follow``) in 8 bits or 16."""
    from .stripes import StripeOptions, extract_stripe_centres

    t0 = time.perf_counter()
    for img, min_peak in _other_frames(deep):
        for detector, method in product(("ridge", "band"), ("cog", "gaussian")):
            if not deep and detector == "ridge" and method == "cog":
                continue  # the default warm-up's (_stripes)
            for im, axis in product((img, np.ascontiguousarray(np.swapaxes(img, 0, 1))),
                                    ("auto", "columns", "rows")):
                extract_stripe_centres(im, options=StripeOptions(
                    detector=detector, method=method, axis=axis, min_peak=min_peak))
    fade = _red_frame(tiny_stripe_frame())
    fade[:, 40:, 1] = fade[:, 40:, 2] = fade[:, 40:, 0]  # its colour lost from column 40
    img, min_peak = (fade.astype(np.uint16) * 257, 1285.0) if deep else (fade, 5.0)
    for axis in ("columns", "rows"):
        im = img if axis == "columns" else np.ascontiguousarray(np.swapaxes(img, 0, 1))
        extract_stripe_centres(im, options=StripeOptions(
            colour="red", axis=axis, centre_on="laser", follow=True, min_peak=min_peak))
    return time.perf_counter() - t0


def _carver() -> float:
    from .octree import warm_up

    return warm_up()


def _geometry() -> float:
    """The triangulation's ray-sheet kernel and the silhouette term's first pass
    (:func:`robo3d.registration._rim_residuals`) on a few points of a tiny view, as the
    triangulate and align stages call them."""
    from .registration import _RIM, _RIM_CELL_PX, SilhouetteViews, _rim_residuals, _view_fields
    from .sim.rig import default_camera, default_laser_mount, look_at
    from .triangulation import triangulate_pixels

    t0 = time.perf_counter()
    cam = default_camera(64, 48)
    triangulate_pixels(np.array([[30.5, 20.25], [31.5, 20.5]]), cam, default_laser_mount())
    mask = np.zeros((48, 64), dtype=bool)
    mask[12:36, 16:48] = True
    T = look_at(np.array([0.0, 0.0, 0.3]), np.zeros(3))
    views = SilhouetteViews([np.where(mask, 180.0, 30.0)], [mask], [cam], T[None])
    field = _view_fields(views, _RIM_CELL_PX, 0.7)[0]
    x = np.array([[0.01, 0.0, 0.0], [0.0, 0.01, 0.0]])
    _rim_residuals(field, x, np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),
                   np.zeros(2, dtype=np.int64), **_RIM)
    return time.perf_counter() - t0


def compile_kernels(processes: int = 2, all_types: bool = False) -> dict[str, float]:
    """Compile (or load from the cache) the detector's, the carver's and the geometry's
    (triangulation, silhouette term) kernels.

    Parameters
    ----------
    processes : int
        Side by side in this many processes (1: one after the other, in this one).
    all_types : bool
        Also the detector on 16-bit and float frames (``stripes_deep``) and with its
        other methods (``stripes_methods``), beside the 8-bit detector.

    Returns
    -------
    dict
        Seconds each part took (``stripes``, ``carver``, ``geometry``, and
        ``stripes_deep``, ``stripes_methods`` when asked) and in all (``total``).
    """
    t0 = time.perf_counter()
    parts = {"stripes": _stripes, "carver": _carver, "geometry": _geometry}
    if all_types:
        # in this order two processes share it evenly: the 8-bit detector (82 s of a cold
        # cache on a 2-core Intel Xeon) and then its other methods (21 s, reusing its
        # kernels) in one, the 16-bit and float frames (about 90 s) and then the rest in
        # the other
        parts = {"stripes": _stripes, "stripes_deep": partial(_stripes_other, True),
                 "stripes_methods": partial(_stripes_other, False), "carver": _carver,
                 "geometry": _geometry}
    if processes <= 1:
        out = {name: fn() for name, fn in parts.items()}
    else:
        with ProcessPoolExecutor(min(processes, len(parts)),
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {name: pool.submit(fn) for name, fn in parts.items()}
            out = {name: f.result() for name, f in futures.items()}
    out["total"] = time.perf_counter() - t0
    return out
