"""The ``foxglove`` stage: a recording's clouds and meshes as one MCAP file for Foxglove
(:mod:`robo3d.foxglove`), on the recording's own clock.

Opened together with the recording, ``results.mcap`` shows each sweep's laser points
(raw and aligned, coloured by sweep) when the sweep's last frame was taken, each laser
frame's profile at its own time, and the meshes at the end of the acquisition (the final
mesh coloured by where its surface came from, the visual hull translucent), all in
``base``. The recording's ``/tf`` holds ``base``; when the config maps ``base`` to another
recorded name (``frames.base: base_link``), an identity ``base_link -> base`` on
``/results/tf_static`` joins the two trees.

The stage writes no ``reports/foxglove.json``: ``evaluate`` gathers every report it finds,
and this stage runs beside it, not before it. What it wrote is in its log and in the
file's own ``robo3d.results`` metadata record.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

import numpy as np

from ..fusion import HULL, MEASURED
from .common import code_version, summary, sweep_color
from .fuse import source_colors

#: Each mesh the config's ``foxglove.meshes`` may name: (topic, what it shows).
MESH_TOPICS = {"mesh": ("/results/mesh", "final mesh (mesh.ply), coloured by source: grey "
                        "measured by the laser, orange inferred from the hull, yellow filled"),
               "hull": ("/results/hull", "visual hull (hull.ply), translucent orange"),
               "fused": ("/results/fused", "fused surface (fused.ply), coloured by source"),
               "measured": ("/results/measured", "laser-measured surface alone (measured.ply)")}
#: The translucent colour of the hull (the provenance colour of hull-inferred surface).
HULL_RGBA = (*(int(x) for x in source_colors(np.array([HULL]))[0]), 90)
#: The colour of the laser-measured surface.
MEASURED_RGB = tuple(int(x) for x in source_colors(np.array([MEASURED]))[0])


def stage_foxglove(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Write ``outputs["mcap"]`` from the recording's results.

    ``inputs``: ``stripes`` (laser frames' stamps), ``clouds``, ``aligned`` (when the
    recording has laser frames), ``silhouettes`` (views' stamps, when it has views) and
    one PLY per entry of ``foxglove.meshes`` that the recording has (``mesh``, ``hull``,
    ``fused``, ``measured``). Returns what was written (messages per topic, points,
    triangles, seconds)."""
    from ..artefacts import Silhouettes, Stripes, load_clouds_npz
    from ..foxglove import FoxgloveOptions, sweep_cloud_messages, write_results_mcap

    t0 = time.perf_counter()
    opts = FoxgloveOptions.from_config(cfg["foxglove"])
    laser = Stripes.load(inputs["stripes"]).stamps_ns if inputs.get("stripes") else None
    views = Silhouettes.load(inputs["silhouettes"]).stamps_ns \
        if inputs.get("silhouettes") else None
    stamps = np.concatenate([s for s in (laser, views) if s is not None] or
                            [np.zeros(1, np.int64)]).astype(np.int64)
    start, end = int(stamps.min()), int(stamps.max())
    palette = np.array([sweep_color(k) for k in range(10)], dtype=np.uint8)
    messages, points = [], {}
    for key, topic in (("clouds", "/results/raw"), ("aligned", "/results/aligned")):
        if inputs.get(key) and laser is not None:
            clouds = load_clouds_npz(inputs[key])
            points[key] = int(sum(len(c) for c in clouds))
            messages += sweep_cloud_messages(
                clouds, laser, topic, palette, options=opts,
                profile_topic="/results/aligned/profile" if key == "aligned" else None)
    messages, triangles = _mesh_messages(inputs, end, messages)
    base_name = str(cfg["frames"]["base"])
    topics = {m.topic for m in messages}
    meta = {"recording": rec_name, "frame_id": "base", "recording_base_frame": base_name,
            "clock": "the recording's: the laser frames' and views' timestamps",
            "robo3d": code_version(),
            "topics": "; ".join(f"{t}: {_describe(t)}" for t in sorted(topics))}
    counts = write_results_mcap(
        outputs["mcap"], messages, metadata={"robo3d.results": meta},
        static_links=[(base_name, "base")] if base_name != "base" else [],
        static_stamp_ns=start)
    report = {"messages": counts, "points": points, "triangles": triangles,
              "time_range_ns": [start, end], "seconds": round(time.perf_counter() - t0, 3)}
    summary.info("results.mcap: %d messages on %d topics, %s points, %s triangles (%.1f s)",
                 sum(counts.values()), len(counts), sum(points.values()),
                 sum(triangles.values()), report["seconds"])
    return report


def _mesh_messages(inputs: Mapping[str, str], stamp_ns: int, messages: list
                   ) -> tuple[list, dict[str, int]]:
    """``messages`` and one SceneUpdate per mesh input, at ``stamp_ns``; the triangles of
    each."""
    from ..foxglove import ResultMessage, scene_update
    from ..meshio import read_mesh, read_vertex_attributes

    triangles = {}
    for key, (topic, what) in MESH_TOPICS.items():
        if not inputs.get(key):
            continue
        V, F = read_mesh(inputs[key])
        if key == "hull":
            colours: Any = HULL_RGBA
        elif key == "measured":
            colours = MEASURED_RGB
        else:
            source = read_vertex_attributes(inputs[key]).get("source")
            colours = source_colors(source) if source is not None else (190, 190, 190)
        messages.append(ResultMessage(topic, stamp_ns, scene_update(
            key, V, F, stamp_ns, colors=colours, metadata={"what": what,
                                                           "faces": str(len(F))})))
        triangles[key] = len(F)
    return messages, triangles


def _describe(topic: str) -> str:
    """What a topic of results.mcap holds, for the file's metadata."""
    for top, what in MESH_TOPICS.values():
        if topic == top:
            return what
    if topic == "/results/aligned/profile":
        return "each laser frame's aligned points, at the frame's time"
    kind = "aligned" if topic.startswith("/results/aligned/") else "raw (before alignment)"
    return f"one sweep's {kind} laser points at its last frame's time, coloured by sweep"
