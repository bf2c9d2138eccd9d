"""Inspection logs in rerun (``.rrd``), one file per stage, one recording id per recording.

Every stage of one recording logs under the same application id (``robo3d``) and the same
recording id (derived from the recording's name), so ``robo3d view <rec>`` (or ``rerun
results/<rec>/*.rrd``) merges them into one scene. Everything is logged in the ``base``
frame (z up), with each camera as a pinhole under its pose, so images, masks and stripe
pixels sit where they were taken.

The entity tree the stages share (:mod:`robo3d.view` lays it out):

- ``base/<stage>/...``: what each stage made in 3D, one subtree per stage (``base/carve/hull``,
  ``base/align/sweep_00``, ``base/simplify/mesh``, ...), so a stage is shown or hidden as
  one;
- ``base/silhouettes/camera``, ``base/stripes/camera``: the current image of each kind, one
  entity whose pose, image and overlay (mask, stripe pixels) change along the timelines;
- ``reports/<stage>``: a short summary of what the stage measured (the whole report is
  ``reports/<stage>.json`` beside the logs), ``reports/summary`` the scan's key figures;
- ``metrics/...``: scalars along the timelines.

Timelines (:data:`TIMELINES`): ``time`` is the recording's own clock; ``view``, ``frame``
and ``sweep`` index the silhouette views, the laser frames and the sweeps.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from typing import Any

import numpy as np

from .atomic import atomic_path
from .camera import CameraModel

__all__ = [
    "APPLICATION_ID",
    "TIMELINES",
    "MASK_CLASS",
    "recording_id",
    "set_image_time",
    "log_scalar",
    "log_text",
    "display_gain",
    "display_image",
    "rerun_log",
    "log_camera",
    "log_points",
    "log_mesh",
    "log_voxels",
    "log_box",
    "log_report",
    "report_markdown",
    "scan_summary_markdown",
    "spaced_indices",
    "format_counts",
]

APPLICATION_ID = "robo3d"
#: The timelines the stages log on: the recording's clock, then the indices of the
#: silhouette views, the laser frames and the sweeps.
TIMELINES = ("time", "view", "frame", "sweep")
#: The class id of a silhouette in the masks (``SegmentationImage``); 0 is background.
MASK_CLASS = 1
#: The colours that mean something everywhere in the view.
MASK_RGBA = (40, 230, 120, 255)
STRIPE_RGB = (0, 255, 255)
#: Stripe centres found only by the faint search (:mod:`robo3d.stripes`, step 9): orange.
FAINT_STRIPE_RGB = (255, 140, 0)


def recording_id(rec_name: str) -> str:
    """The rerun recording id shared by every stage of one recording (deterministic)."""
    return str(uuid.uuid5(uuid.NAMESPACE_URL, f"robo3d/recording/{rec_name}"))


@contextlib.contextmanager
def rerun_log(path: str | os.PathLike[str], rec_name: str) -> Iterator[Any]:
    """A rerun stream saving to ``path`` atomically; yields the ``RecordingStream``.

    The file appears only when the block completes; on an exception it is removed.
    """
    import rerun as rr

    with atomic_path(path) as tmp:
        stream = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id(rec_name))
        # no wall-clock "log_time" timeline: the stages log on the recording's clock
        # and indices (TIMELINES) only
        stream.set_log_time_enabled(False)
        # the time a stream logs at is kept per thread and recording id, which the stages
        # of one recording share: start from none (stages run in one process in tests)
        stream.reset_time()
        stream.save(str(tmp))
        stream.log("base", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        # the masks' classes (background transparent), for every image under base
        stream.log("base", rr.AnnotationContext([(0, "background", (0, 0, 0, 0)),
                                                 (MASK_CLASS, "silhouette", MASK_RGBA)]),
                   static=True)
        try:
            yield stream
        finally:
            stream.reset_time()
            stream.flush()
            stream.disconnect()


def spaced_indices(n: int, at_most: int) -> np.ndarray:
    """At most ``at_most`` indices evenly spaced over ``range(n)`` (all if ``n <= at_most``)."""
    if at_most <= 0 or n == 0:
        return np.zeros(0, dtype=int)
    if n <= at_most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, at_most).round().astype(int))


def set_image_time(stream: Any, timestamp_ns: int | None = None, **indices: int) -> None:
    """Place what is logged next on the timelines: ``time`` at ``timestamp_ns`` (the
    recording's clock, when known) and each index given (``view=3``, ``frame=17``,
    ``sweep=1``; names from :data:`TIMELINES`), so that one image, its overlay and the
    scalars of the same moment line up whichever timeline the viewer scrubs."""
    for name in indices:
        if name not in TIMELINES:
            raise ValueError(f"timeline must be one of {TIMELINES}, got {name!r}")
    if timestamp_ns is not None:
        stream.set_time("time", timestamp=np.datetime64(int(timestamp_ns), "ns"))
    for name, i in indices.items():
        stream.set_time(name, sequence=int(i))


def log_scalar(stream: Any, entity: str, value: float) -> None:
    """Log one scalar at the current time (a point of a time series, ``metrics/...``)."""
    import rerun as rr

    stream.log(entity, rr.Scalars([float(value)]))


def log_text(stream: Any, entity: str, markdown: str) -> None:
    """Log a short markdown document (a summary a person reads), static."""
    import rerun as rr

    stream.log(entity, rr.TextDocument(markdown, media_type="text/markdown"), static=True)


def _as_8bit_scale(image: np.ndarray) -> np.ndarray:
    """An image's values on the 0-255 scale of 8-bit pixels (16-bit divided by 257, float
    images taken as 0-1), as float32."""
    a = np.asarray(image)
    if a.dtype == np.uint16:
        return a.astype(np.float32) / 257.0
    if np.issubdtype(a.dtype, np.floating):
        return a.astype(np.float32) * 255.0
    return a.astype(np.float32)


def display_gain(images: list[np.ndarray], *, bright: float = 128.0,
                 max_gain: float = 16.0) -> float:
    """The brightness gain that makes dim laser frames legible on screen: the brightest
    of the images' 99.9th percentiles (on the 8-bit scale) is brought to ``bright``
    (never darkened, at most ``max_gain`` times). One gain for a recording's frames, so
    that they compare; the stripe's pixels come from the recorded frames, not these."""
    if not images:
        return 1.0
    ref = max(_high_percentile(im, 99.9) for im in images)
    return float(np.clip(bright / max(ref, 1.0), 1.0, max_gain))


def _high_percentile(image: np.ndarray, q: float) -> float:
    """The ``q``-th percentile of an image's values on the 8-bit scale; for 8-bit images
    from a histogram (one pass, no sort: ``np.percentile`` on 40 full 1280 x 960 frames
    cost about a second per recording), the smallest level reaching the fraction."""
    a = np.asarray(image)
    if a.dtype != np.uint8:
        return float(np.percentile(_as_8bit_scale(a), q))
    cum = np.cumsum(np.bincount(a.ravel(), minlength=256))
    return float(np.searchsorted(cum, q / 100.0 * cum[-1]))


def display_image(image: np.ndarray, gain: float = 1.0) -> np.ndarray:
    """An image as 8-bit pixels for the screen, brightened by ``gain``
    (:func:`display_gain`)."""
    return np.clip(_as_8bit_scale(image) * gain, 0, 255).astype(np.uint8)


def log_camera(stream: Any, entity: str, camera: CameraModel, T_base_camera: np.ndarray, *,
               image: np.ndarray | None = None, encoded: tuple[bytes, str] | None = None,
               mask: np.ndarray | None = None, points_uv: np.ndarray | None = None,
               static: bool = True, image_plane_distance: float = 0.05,
               points_color: Any = STRIPE_RGB) -> None:
    """Log a camera frustum at its pose with, optionally, its image (raw array or
    ``(bytes, media_type)`` as recorded), a silhouette mask (class :data:`MASK_CLASS`,
    drawn over the image) and 2-D points (stripe pixels, in ``points_color``)."""
    import rerun as rr

    T = np.asarray(T_base_camera, dtype=np.float64)
    stream.log(entity, rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]), static=static)
    stream.log(entity, rr.Pinhole(image_from_camera=camera.K, resolution=[camera.width,
                                                                           camera.height],
                                  camera_xyz=rr.ViewCoordinates.RDF,
                                  image_plane_distance=image_plane_distance), static=static)
    if encoded is not None:
        data, media_type = encoded
        stream.log(f"{entity}/image", rr.EncodedImage(contents=data, media_type=media_type),
                   static=static)
    elif image is not None:
        stream.log(f"{entity}/image", rr.Image(image), static=static)
    if mask is not None:
        classes = (np.asarray(mask) > 0).astype(np.uint8) * np.uint8(MASK_CLASS)
        stream.log(f"{entity}/mask", rr.SegmentationImage(classes, opacity=0.35,
                                                          draw_order=1.0), static=static)
    if points_uv is not None:
        stream.log(f"{entity}/points", rr.Points2D(np.asarray(points_uv, dtype=np.float32),
                                                   radii=0.8, colors=points_color,
                                                   draw_order=2.0),
                   static=static)


def log_points(stream: Any, entity: str, points: np.ndarray, *, colors: Any = None,
               radii: float = 0.0003, static: bool = True) -> None:
    """Log a point cloud (``(N, 3)`` metres, base frame)."""
    import rerun as rr

    stream.log(entity, rr.Points3D(np.asarray(points, dtype=np.float32), colors=colors,
                                   radii=radii), static=static)


def log_mesh(stream: Any, entity: str, vertices: np.ndarray, faces: np.ndarray, *,
             vertex_normals: np.ndarray | None = None, vertex_colors: Any = None,
             albedo: Any = None, static: bool = True) -> None:
    """Log a triangle mesh (base frame)."""
    import rerun as rr

    stream.log(entity, rr.Mesh3D(vertex_positions=np.asarray(vertices, dtype=np.float32),
                                 triangle_indices=np.asarray(faces, dtype=np.uint32),
                                 vertex_normals=None if vertex_normals is None else
                                 np.asarray(vertex_normals, dtype=np.float32),
                                 vertex_colors=vertex_colors, albedo_factor=albedo),
               static=static)


def log_voxels(stream: Any, entity: str, centres: np.ndarray, voxel_size: float, *,
               colors: Any = (120, 160, 220), max_voxels: int = 200_000,
               static: bool = True) -> None:
    """Log occupied voxels as boxes (the surface shell when there are too many)."""
    import rerun as rr

    c = np.asarray(centres, dtype=np.float32)
    if len(c) > max_voxels:
        c = c[spaced_indices(len(c), max_voxels)]
    half = np.full((len(c), 3), voxel_size / 2, dtype=np.float32)
    stream.log(entity, rr.Boxes3D(centers=c, half_sizes=half, colors=colors,
                                  fill_mode="solid"), static=static)


def log_box(stream: Any, entity: str, box_min: np.ndarray, box_max: np.ndarray, *,
            label: str | None = None, color: Any = (150, 150, 150), static: bool = True
            ) -> None:
    """Log an axis-aligned box (workspace, carving box) as a thin wireframe (a label, if
    given, shows only when the box is selected: over the object it hides what matters)."""
    import rerun as rr

    lo, hi = np.asarray(box_min, dtype=np.float32), np.asarray(box_max, dtype=np.float32)
    stream.log(entity, rr.Boxes3D(mins=[lo], sizes=[hi - lo], colors=[color], radii=0.0002,
                                  labels=[label] if label else None,
                                  show_labels=False if label else None),
               static=static)


def _cell(value: Any) -> str | None:
    """A report value as a table cell, or None when it is not a short one."""
    if isinstance(value, bool) or value is None:
        return str(value).lower()
    if isinstance(value, (int, np.integer)):
        return f"{int(value):,}"
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.4g}"
    if isinstance(value, str):
        return value if len(value) <= 80 else value[:77] + "..."
    if isinstance(value, (list, tuple)) and len(value) <= 4 and all(
            isinstance(v, (int, float, str, np.number)) for v in value):
        return ", ".join(_cell(v) or "" for v in value)
    return None


def report_markdown(title: str, report: dict[str, Any], *, max_rows: int = 24) -> str:
    """A stage's report as a short markdown table a person reads: its short values, and
    those of its sections one level down (``dropped / outside workspace``); lists and
    deeper sections are left to the JSON report beside the logs."""
    rows: list[tuple[str, str]] = []
    for key, value in report.items():
        cell = _cell(value)
        if cell is not None:
            rows.append((key.replace("_", " "), cell))
        elif isinstance(value, dict):
            for sub, v in value.items():
                c = _cell(v)
                if c is not None:
                    rows.append((f"{key.replace('_', ' ')} / {str(sub).replace('_', ' ')}", c))
    more = len(rows) - max_rows
    lines = [f"### {title}", "", "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in rows[:max_rows]]
    if more > 0:
        lines.append(f"| ... | {more} more rows |")
    lines += ["", "Everything the stage measured: its JSON report in `reports/` beside "
              "the logs."]
    return "\n".join(lines)


def log_report(stream: Any, entity: str, report: dict[str, Any]) -> None:
    """Log a stage's report (what it measured) as a short markdown table
    (:func:`report_markdown`), not raw JSON: the viewer is for reading at a glance."""
    log_text(stream, entity, report_markdown(entity.rsplit("/", 1)[-1], report))


def format_counts(counts: dict[str, int], none: str = "none") -> str:
    """Counts by reason as words for a log line: ``{"grazing": 0, "outside_workspace":
    5415}`` -> ``"5415 outside workspace"`` (zeros left out; ``none`` when all are)."""
    parts = [f"{int(n)} {k.replace('_', ' ')}" for k, n in counts.items() if int(n)]
    return ", ".join(parts) if parts else none


def _fmt(value: Any, spec: str = ".3g", unit: str = "") -> str:
    """A number for the summary, or a dash when the figure is missing."""
    if value is None or isinstance(value, (dict, list)):
        return "-"
    try:
        return f"{float(value):{spec}}{unit}"
    except (TypeError, ValueError):
        return str(value)


def _scaled(value: Any, factor: float) -> float | None:
    return None if value is None else factor * float(value)


def _percent(fraction: Any) -> float | None:
    return _scaled(fraction, 100.0)


def _sweep_rows(metrics: dict[str, Any]) -> list[str]:
    """The per-sweep table of the summary: points, the alignment's correction and, with
    ground truth, the pose error after alignment."""
    stages = metrics.get("stages", {})
    tri = {r.get("sweep"): r for r in stages.get("triangulate", {}).get("sweeps", []) or []}
    ali = {r.get("sweep"): r for r in stages.get("align", {}).get("per_sweep", []) or []}
    ev = {r.get("sweep"): r for r in (metrics.get("evaluation", {}).get("poses", {})
                                      .get("per_sweep", []) or [])}
    sweeps = sorted(k for k in set(tri) | set(ali) if k is not None)
    if not sweeps:
        return []
    rows = ["", "| sweep (colour) | points | correction | pose error after |",
            "|---|---|---|---|"]
    for k in sweeps:
        r, a, e = tri.get(k, {}), ali.get(k, {}), ev.get(k, {})
        rows.append(f"| {k} ({SWEEP_NAMES[int(k) % len(SWEEP_NAMES)]}) | "
                    f"{_fmt(r.get('points'), ',.0f')} | "
                    f"{_fmt(a.get('translation_mm'), '.3f', ' mm')}, "
                    f"{_fmt(a.get('rotation_deg'), '.3f', ' deg')} | "
                    f"{_fmt(e.get('after_mm'), '.3f', ' mm')}, "
                    f"{_fmt(e.get('after_deg'), '.3f', ' deg')} |")
    return rows


#: The sweeps' colours (``robo3d.stages.common.sweep_color``) and their names for the legend.
SWEEP_RGB = [(230, 25, 75), (60, 180, 75), (0, 130, 200), (245, 130, 48), (145, 30, 180),
             (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 212), (0, 128, 128)]
SWEEP_NAMES = ["red", "green", "blue", "orange", "purple", "cyan", "magenta", "lime", "pink",
               "teal"]


def scan_summary_markdown(rec_name: str, metrics: dict[str, Any], *,
                          error_vmax_mm: float | None = None) -> str:
    """The scan's key figures from ``metrics.json`` as a short markdown document for the
    viewer (``reports/summary``): what was used, how much the laser measured, the
    accuracy against ground truth when there is one, the time; then the colours'
    meaning. Missing figures (a skipped stage) show as a dash."""
    st = metrics.get("stages", {})
    ev = metrics.get("evaluation", {}) or {}
    carve, tri, simp = st.get("carve", {}), st.get("triangulate", {}), st.get("simplify", {})
    stripes = st.get("stripes", {})
    used, left = carve.get("views_used"), carve.get("views_left_out") or []
    mesh_src = (metrics.get("surface_sources", {}) or {}).get("mesh", {}) or {}
    rows = [
        ("views carved", f"{len(used)} of {carve.get('n_views', '-')}"
         + (f" (left out: {', '.join(str(r.get('view', r)) for r in left)})" if left else "")
         if used is not None else "-"),
        ("hull", f"{_fmt(_scaled(carve.get('volume_m3'), 1e6), '.1f', ' cm³')}, IoU with "
                 f"truth {_fmt(ev.get('hull_volume_iou'), '.3f')}"),
        ("stripe points", f"{_fmt(stripes.get('n_points'), ',.0f')} in "
                          f"{_fmt(stripes.get('n_frames'), ',.0f')} frames"),
        ("laser points", f"{_fmt(tri.get('n_points'), ',.0f')} in "
                         f"{_fmt(tri.get('n_sweeps'), '.0f')} sweeps"),
        ("final mesh", f"{_fmt(simp.get('n_faces'), ',.0f')} faces; measured by the laser "
                       f"{_fmt(_percent(mesh_src.get('measured')), '.1f', ' %')} of its area"),
    ]
    measured = ev.get("measured", {}) or {}
    mesh = ev.get("mesh", {}) or {}
    if measured or mesh:
        comp = (mesh.get("completeness", {}) or {}).get("within_mm", {}) or {}
        rows += [("measured surface vs truth", f"median {_fmt(measured.get('median_mm'), '.3f')}"
                  f" mm, p95 {_fmt(measured.get('p95_mm'), '.3f')} mm"),
                 ("completeness within 0.5 mm", _fmt(_percent(comp.get("0.5")), ".1f", " %"))]
    total = (metrics.get("timings", {}) or {}).get("total_seconds")
    rows.append(("time, all stages", _fmt(total, '.1f', ' s')))
    lines = [f"### {rec_name}", "", "| | |", "|---|---|"]
    lines += [f"| {k} | {v} |" for k, v in rows]
    lines += _sweep_rows(metrics)
    mesh_colour = (f"blue 0 mm to red {error_vmax_mm:g} mm and beyond: distance to the "
                   "true surface" if ev and error_vmax_mm else
                   "grey measured by the laser, orange inferred from the hull, yellow "
                   "filled")
    lines += ["", "**Colours.** Clouds: one colour per sweep (table). Final mesh: "
              f"{mesh_colour}. Hull: translucent orange (inferred). Masks: green over "
              "the view. Stripe pixels: cyan over the laser frame (brightened for the "
              "screen).", "",
              "Hidden at first (tick them in the blueprint panel): ground truth, raw "
              "sweeps, every camera, voxels, boxes, the fused mesh."]
    skipped = metrics.get("skipped") or {}
    if skipped:
        lines += ["", "Skipped: " + "; ".join(f"{k}: {v}" for k, v in skipped.items())]
    return "\n".join(lines)
