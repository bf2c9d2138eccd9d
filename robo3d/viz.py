"""Inspection logs in rerun (``.rrd``), one file per stage, one recording id per recording.

Every stage of one recording logs under the same application id (``robo3d``) and the same
recording id (derived from the recording's name), so ``rerun results/<rec>/*.rrd`` merges
them into one scene. Everything is logged in the ``base`` frame (z up), with each camera as
a pinhole under its pose, so images, masks and stripe pixels sit where they were taken.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from collections.abc import Iterator
from typing import Any

import numpy as np

from .atomic import atomic_path, dumps_json
from .camera import CameraModel

__all__ = [
    "recording_id",
    "rerun_log",
    "log_camera",
    "log_points",
    "log_mesh",
    "log_voxels",
    "log_box",
    "log_report",
    "spaced_indices",
    "format_counts",
]

APPLICATION_ID = "robo3d"


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
        stream.save(str(tmp))
        stream.log("base", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        try:
            yield stream
        finally:
            stream.flush()
            stream.disconnect()


def spaced_indices(n: int, at_most: int) -> np.ndarray:
    """At most ``at_most`` indices evenly spaced over ``range(n)`` (all if ``n <= at_most``)."""
    if at_most <= 0 or n == 0:
        return np.zeros(0, dtype=int)
    if n <= at_most:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, at_most).round().astype(int))


def log_camera(stream: Any, entity: str, camera: CameraModel, T_base_camera: np.ndarray, *,
               image: np.ndarray | None = None, encoded: tuple[bytes, str] | None = None,
               mask: np.ndarray | None = None, points_uv: np.ndarray | None = None,
               static: bool = True, image_plane_distance: float = 0.05) -> None:
    """Log a camera frustum at its pose with, optionally, its image (raw array or
    ``(bytes, media_type)`` as recorded), a silhouette mask and 2-D points (stripe pixels)."""
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
        stream.log(f"{entity}/mask", rr.SegmentationImage(np.asarray(mask, dtype=np.uint8),
                                                          opacity=0.4), static=static)
    if points_uv is not None:
        stream.log(f"{entity}/points", rr.Points2D(np.asarray(points_uv, dtype=np.float32),
                                                   radii=0.8, colors=[255, 40, 40]),
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
            label: str | None = None, static: bool = True) -> None:
    """Log an axis-aligned box (workspace, carving box) as wireframe."""
    import rerun as rr

    lo, hi = np.asarray(box_min, dtype=np.float32), np.asarray(box_max, dtype=np.float32)
    stream.log(entity, rr.Boxes3D(mins=[lo], sizes=[hi - lo], labels=[label] if label else None),
               static=static)


def log_report(stream: Any, entity: str, report: dict[str, Any]) -> None:
    """Log a stage's report (what it measured) as a markdown document."""
    import rerun as rr

    text = "```json\n" + dumps_json(report) + "\n```"
    stream.log(entity, rr.TextDocument(text, media_type="text/markdown"), static=True)


def format_counts(counts: dict[str, int], none: str = "none") -> str:
    """Counts by reason as words for a log line: ``{"grazing": 0, "outside_workspace":
    5415}`` -> ``"5415 outside workspace"`` (zeros left out; ``none`` when all are)."""
    parts = [f"{int(n)} {k.replace('_', ' ')}" for k, n in counts.items() if int(n)]
    return ", ".join(parts) if parts else none
