"""Helpers the stage modules share: reading a recording with the config's reader options,
camera and workspace arrays of the artefacts, progress lines, thread counts.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ..artefacts import (  # noqa: F401 - the three array helpers: re-exported
    Silhouettes,
    camera_arrays,
    cameras_from,
    workspace_from,
)
from ..errors import StageError

log = logging.getLogger("robo3d.pipeline")
#: The one-line summaries of the stages (and their progress): what the terminal shows.
summary = logging.getLogger("robo3d.summary")


# ---------------------------------------------------------------------------- helpers
def open_recording(path: str, cfg: Mapping[str, Any], roles: tuple[str, ...], require: bool = True,
                   calibration: str | None = None):
    """Read a recording with the config's reader options; with ``calibration`` (a
    ``results/calibration/<calib>.yaml``, config key ``scan_calibration``) its camera
    model, hand-eye and laser replace the recorded ones
    (:func:`robo3d.calibration.io.apply_calibration`)."""
    from ..recording.reader import read_recording

    rec = read_recording(path, roles=roles, require=require, **reader_options(cfg))
    if calibration:
        from ..calibration.io import CALIBRATION_METADATA, apply_calibration

        rec = apply_calibration(rec, calibration)
        log.info("%s: using calibration %s (%s)", path, calibration,
                 rec.metadata[CALIBRATION_METADATA]["replaced"])
    return rec  # the reader has logged its warnings (rec.warnings keeps them)


def reader_options(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The reader's keyword arguments from a config's topics, frames and timing sections:
    recorded frame names are renamed to their roles, so poses are looked up in ``base``."""
    timing = cfg.get("timing", {})
    return {"topics": topic_map(cfg.get("topics")),
            "frames": dict(cfg.get("frames") or {}),
            "base_frame": "base",
            "max_pose_gap_ns": int(round(timing.get("max_pose_gap_s", 0.05) * 1e9)),
            "stamp_source": timing.get("stamp_source", "header"),
            "image_offset_ns": int(round(timing.get("image_offset_s", 0.0) * 1e9))}


def media_type(encoding: str) -> str | None:
    return {"png": "image/png", "jpeg": "image/jpeg"}.get(encoding)


def log_image_camera(stream, entity, msg, camera, T, decode=None, **kw) -> None:
    """The image of ``msg`` at its camera: its recorded bytes where they are PNG or JPEG,
    else (or with ``decode``, the recording's :meth:`~robo3d.recording.model.Recording.
    decode` for a rectified camera, whose recorded bytes are the raw image) decoded."""
    from ..viz import log_camera

    mt = media_type(msg.encoding)
    if decode is not None:
        log_camera(stream, entity, camera, T, image=decode(msg), **kw)
    elif mt is not None:
        log_camera(stream, entity, camera, T, encoded=(msg.data, mt), **kw)
    else:
        log_camera(stream, entity, camera, T, image=msg.decode(), **kw)


class Progress:
    """Logs progress of a loop over frames every few seconds (users watch long work)."""

    def __init__(self, what: str, total: int, every_s: float = 10.0) -> None:
        self.what, self.total, self.every = what, total, every_s
        self.t0 = self.last = time.perf_counter()

    def __call__(self, done: int) -> None:
        now = time.perf_counter()
        if now - self.last >= self.every or done == self.total:
            self.last = now
            dt = max(now - self.t0, 1e-9)
            rate = done / dt
            eta = (self.total - done) / rate if rate > 0 else float("nan")
            speed = f"{rate:.0f}/s" if rate >= 10 else f"{rate:.2g}/s" if rate >= 0.1 else \
                f"{dt / max(done, 1):.0f} s each"
            left = f", about {eta:.0f} s left" if done < self.total and eta == eta else ""
            summary.info("%s: %d/%d (%s%s)", self.what, done, self.total, speed, left)


def load_silhouettes(path: str) -> dict[str, Any]:
    """The arrays of a ``silhouettes.npz``, the masks unpacked (the layout of
    :meth:`robo3d.artefacts.Silhouettes.as_arrays`)."""
    return Silhouettes.load(path).as_arrays()


def mesh_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Enclosed volume of a closed, outward-wound triangle mesh, cubic metres."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def laser_poses(rec, frames: list, laser_frame: str = "laser") -> np.ndarray:
    """``T_camera_laser`` (F, 4, 4) of each laser frame at its own time, looked up once per
    camera frame_id (vectorised over the frames' stamps)."""
    out = np.zeros((len(frames), 4, 4))
    if not frames:
        return out
    ids = np.array([str(m.frame_id) for m in frames])
    stamps = np.array([m.timestamp_ns for m in frames], dtype=np.int64)
    for fid in np.unique(ids):
        sel = np.nonzero(ids == fid)[0]
        out[sel] = rec.tf.lookup(str(fid), laser_frame, stamps[sel])
    return out


def sweeps_of(stamps_ns: np.ndarray, cfg: Mapping[str, Any]) -> np.ndarray:
    """Each laser frame's sweep by the config's ``timing`` (``sweep_gap_s``,
    ``sweep_gap_intervals``; :func:`robo3d.triangulation.split_sweeps`): the stripes
    stage's rerun timeline and the triangulation split them the same way."""
    from ..triangulation import split_sweeps

    timing = cfg["timing"]
    return split_sweeps(np.asarray(stamps_ns, dtype=np.int64),
                        int(round(timing["sweep_gap_s"] * 1e9)),
                        float(timing["sweep_gap_intervals"]))


def stage_threads(threads: int | None) -> int:
    """Worker threads of a stage: the job's (Snakemake's ``threads``) or 1."""
    n = 1 if threads is None else int(threads)
    if n < 1:
        raise StageError(f"threads must be >= 1, got {threads}")
    return n


#: the stages whose algorithms run Open3D (ICP, KD-trees, decimation, mesh distances)
OPEN3D_STAGES = frozenset({"align", "fuse", "simplify", "evaluate"})


def pin_open3d_threads() -> None:
    """Let Open3D use one CPU thread in this process, so that its results do not depend on
    thread timing.

    Open3D parallelises with oneTBB, whose reductions add the partial sums in the order
    the threads finish (``OMP_NUM_THREADS`` does not reach it). Measured on the demo vase's
    alignment: two processes with the same input gave aligned points 1e-16 m apart (the
    symmetric ICP's transform differs in the last bits), and quadric decimation turned that
    into another triangulation of the same surface. With one thread the aligned points are
    byte-identical from run to run; the align stage took 57 s instead of 79 s wall (once, on
    a loaded 2-core machine: TBB's threads only competed with other jobs). Our own kernels
    (numba, thread pools over frames) give the same result at any thread count.
    """
    import open3d as o3d

    o3d.utility.set_max_threads(1)


def sweep_color(k: int) -> list[int]:
    """The colour of sweep ``k`` in every cloud (:data:`robo3d.viz.SWEEP_RGB`)."""
    from ..viz import SWEEP_RGB

    return list(SWEEP_RGB[int(k) % len(SWEEP_RGB)])


def silhouette_views(inputs: Mapping[str, str], cfg: Mapping[str, Any]):
    """The silhouette views (grey images, masks, cameras, poses) for the alignment's
    absolute reference; None when the recording's views cannot be matched."""
    from ..registration import SilhouetteViews

    sil = Silhouettes.load(inputs["silhouettes"])
    cameras = sil.cameras
    if not cameras or not inputs.get("recording"):
        return None
    rec = open_recording(inputs["recording"], cfg, roles=("views",))
    by_stamp = {m.timestamp_ns: m for m in rec.views}
    images = []
    for t in sil.stamps_ns:
        msg = by_stamp.get(int(t))
        if msg is None:
            log.warning("alignment: view at t=%d ns of the silhouettes is not in %s; the "
                        "silhouettes are not used as reference", int(t), inputs["recording"])
            return None
        images.append(rec.decode(msg))
    return SilhouetteViews(images, sil.view_masks(), cameras, sil.T_base_camera)


def topic_map(topics: Mapping[str, str] | None):
    """The :class:`~robo3d.recording.TopicMap` of a config's ``topics`` section."""
    from ..recording import TopicMap

    return TopicMap(**dict(topics or {}))


#: The packages whose versions ``metrics.json`` records (``environment``).
_VERSIONED = ("numpy", "scipy", "opencv-python-headless", "open3d", "numba", "pymeshlab",
              "scikit-image")


def environment() -> dict[str, Any]:
    """What the results were computed with besides robo3d's code: Python, the numeric
    packages' versions and the CPU. The same recording and config give the same files on
    one machine (``benchmarks/determinism.py``); another CPU (its vector units) or
    another release of these packages changes the last bits of floating-point results,
    which the alignment can carry further (``benchmarks/README.md``, stop 32)."""
    import platform
    from importlib import metadata

    versions = {}
    for name in _VERSIONED:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="utf-8") as f:
            cpu = next((ln.split(":", 1)[1].strip() for ln in f
                        if ln.startswith("model name")), cpu)
    except OSError:
        pass
    return {"python": platform.python_version(), "platform": platform.platform(),
            "cpu": cpu, "cpu_count": os.cpu_count(), "packages": versions}


def code_version() -> str:
    """robo3d's version and a hash of its code (every ``.py`` file of the package): part of
    every rule's params, so that an upgrade or a code change re-runs the jobs instead of
    silently keeping results the new code would not give."""
    import hashlib

    from .. import __version__

    root = Path(__file__).resolve().parents[1]
    h = hashlib.sha256()
    for f in sorted(root.rglob("*.py")):
        h.update(str(f.relative_to(root)).encode())
        h.update(f.read_bytes())
    return f"{__version__}+{h.hexdigest()[:16]}"
