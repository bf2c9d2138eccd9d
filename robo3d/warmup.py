"""Compile the pipeline's numba kernels into numba's on-disk cache, once.

A fresh install (or an edit of a module) has no compiled kernels: the first process that
calls one compiles it (the stripe detector's kernels for 8-bit frames: about 40 s of CPU
on a 2-core AMD EPYC; the carver's: about 6 s) and writes it to the cache
(``robo3d/__pycache__``), which later processes load in well under a second. Processes
that start side by side before the cache is written each compile it themselves: a batch
of N recordings on N cores (or N SLURM jobs) pays the compilation N times over, and on a
2-core machine the test suite's end-to-end runs (seven stripe jobs at once) paid about
two minutes for it. ``robo3d warm-up`` compiles them once, the detector and the carver in
two processes side by side, before such a batch starts (``./run.sh`` does it before the
demo and before the tests). Nothing it computes is kept; what the kernels compute is the
same either way.

Only the image types a recording's laser frames decode to (8-bit RGB and mono) are
compiled; other types (16-bit, float) compile at their first use.
"""

from __future__ import annotations

import multiprocessing
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

__all__ = ["compile_kernels", "tiny_stripe_frame"]


def tiny_stripe_frame() -> np.ndarray:
    """A 48 x 64 8-bit mono frame with one slightly tilted Gaussian stripe (peak 200): the
    smallest input that takes the detector through its kernels."""
    yy, xx = np.mgrid[0:48, 0:64]
    return np.clip(np.rint(200.0 * np.exp(-0.5 * ((yy - 20.0 - 0.1 * xx) / 1.5) ** 2)), 0,
                   255).astype(np.uint8)


def _stripes() -> float:
    """The stripe detector on tiny 8-bit RGB and mono frames, the line both ways."""
    from .stripes import StripeOptions, extract_stripe_centres

    t0 = time.perf_counter()
    mono = tiny_stripe_frame()
    rgb = np.stack([mono, np.full_like(mono, 10), np.full_like(mono, 10)], axis=-1)
    opts = StripeOptions(min_peak=5.0)
    for img in (rgb, mono):
        extract_stripe_centres(img, options=opts)
        extract_stripe_centres(np.ascontiguousarray(np.swapaxes(img, 0, 1)), options=opts)
    return time.perf_counter() - t0


def _carver() -> float:
    from .octree import warm_up

    return warm_up()


def compile_kernels(processes: int = 2) -> dict[str, float]:
    """Compile (or load from the cache) the detector's and the carver's kernels.

    Parameters
    ----------
    processes : int
        Side by side in this many processes (1: one after the other, in this one).

    Returns
    -------
    dict
        Seconds each part took (``stripes``, ``carver``) and in all (``total``).
    """
    t0 = time.perf_counter()
    parts = {"stripes": _stripes, "carver": _carver}
    if processes <= 1:
        out = {name: fn() for name, fn in parts.items()}
    else:
        with ProcessPoolExecutor(min(processes, len(parts)),
                                 mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {name: pool.submit(fn) for name, fn in parts.items()}
            out = {name: f.result() for name, f in futures.items()}
    out["total"] = time.perf_counter() - t0
    return out
