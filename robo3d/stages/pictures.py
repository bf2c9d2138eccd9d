"""The ``pictures`` stage: the report's pictures of one recording (:mod:`robo3d.report`):
masks over their images, stripes over laser frames, the hull, the aligned clouds
coloured by sweep, the final mesh coloured by its error (by where its surface came from
when there is no ground truth), the stage timings and memory, and a thumbnail for the
report's overview.

It runs after ``evaluate`` (it reads ``metrics.json`` for the captions and the timings)
and draws only: no figure is computed here that ``metrics.json`` does not hold, except
each final-mesh vertex's distance to the true surface, which is what the colours show.
A stage the recording has no data for gets a picture that says so; a picture that cannot
be drawn from damaged data says why in its place (and in the log), and the others are
still drawn.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ..errors import Robo3dError
from .common import log, open_recording, summary

__all__ = ["stage_pictures", "PICTURES"]

#: The outputs, in the order they are drawn.
PICTURES = ("masks", "stripes", "hull", "clouds", "mesh", "timings", "thumbnail")


def stage_pictures(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Draw every picture of one recording into ``outputs`` (one PNG per key of
    :data:`PICTURES`); returns what each picture shows, and the up axis and how it was
    found (:func:`robo3d.report.find_up`)."""
    from ..artefacts import Silhouettes, Stripes
    from ..meshio import read_mesh
    from ..report import find_up, placeholder, write_png

    t0 = time.perf_counter()
    rc = cfg.get("report", {})
    n_images, tile = int(rc.get("images", 8)), int(rc.get("tile_px", 240))
    with open(inputs["metrics"], encoding="utf-8") as f:
        metrics = json.load(f)
    V, F = read_mesh(inputs["mesh"])
    sil = Silhouettes.load(inputs["silhouettes"]) if inputs.get("silhouettes") else None
    stripes = Stripes.load(inputs["stripes"]) if inputs.get("stripes") else None
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0)) if len(V) else np.zeros(3)
    up, how = find_up(centre, [a.T_base_camera for a in (sil, stripes) if a is not None])
    roles = tuple(r for r, a in (("views", sil), ("laser", stripes)) if a is not None)
    rec = open_recording(inputs["recording"], cfg, roles=roles, require=False,
                         calibration=inputs.get("calibration"))
    drawn: dict[str, str] = {}

    def draw(key: str, make: Callable[[], np.ndarray], missing: str | None = None) -> None:
        if key not in outputs:
            return
        if missing is not None:
            img, drawn[key] = placeholder(missing), missing
        else:
            try:
                img, drawn[key] = make(), "drawn"
            except (Robo3dError, ValueError, KeyError, OSError) as exc:
                msg = f"could not draw the {key} picture: {type(exc).__name__}: {exc}"
                log.warning("%s", msg)
                img, drawn[key] = placeholder(msg[:160]), msg
        write_png(outputs[key], img)

    no_views = "no silhouette views in this recording: no masks, no visual hull"
    no_laser = "no laser frames in this recording: no stripes, no clouds"
    draw("masks", lambda: _masks(rec, sil, metrics, n_images, tile),
         None if sil is not None else no_views)
    draw("stripes", lambda: _stripes(rec, stripes, n_images, tile),
         None if stripes is not None else no_laser)
    draw("hull", lambda: _hull(inputs["hull_mesh"], metrics, up, how, tile),
         None if inputs.get("hull_mesh") else no_views)
    draw("clouds", lambda: _clouds(inputs["aligned"], metrics, up, tile),
         None if inputs.get("aligned") else no_laser)
    mesh_tiles: list[np.ndarray] = []
    draw("mesh", lambda: _mesh(inputs["mesh"], (V, F), rec, metrics, cfg, up, tile,
                               mesh_tiles))
    draw("timings", lambda: _timings(metrics))
    draw("thumbnail", lambda: _thumbnail(mesh_tiles, metrics))
    report = {"up": up.tolist(), "up_found_from": how, "pictures": drawn,
              "seconds": round(time.perf_counter() - t0, 3)}
    summary.info("drew %d pictures in %.1f s (up %s: %s)", len(drawn), report["seconds"],
                 np.round(up, 3).tolist(), how)
    return report


def _masks(rec, sil, metrics: Mapping[str, Any], n: int, tile: int) -> np.ndarray:
    from ..report import masks_picture

    per_view = ((metrics.get("evaluation") or {}).get("mask_iou") or {}).get("per_view") or []
    iou = {int(v["view"]): float(v["iou"]) for v in per_view
           if isinstance(v, dict) and v.get("iou") is not None}
    left = {int(v["view"]) for v in metrics.get("views_left_out") or []
            if isinstance(v, dict) and "view" in v}
    seeded = ((metrics.get("stages") or {}).get("silhouettes") or {}).get("laser_seeded") or {}
    laser = {int(v) for v, c in (seeded.get("candidates") or {}).items()
             if isinstance(c, dict) and c.get("accepted")}
    return masks_picture(rec, sil, n=n, tile_px=tile, mask_iou=iou, left_out=left,
                         from_laser=laser,
                         notes=_surroundings(metrics) + _laser_against_masks(metrics))


def _surroundings(metrics: Mapping[str, Any]) -> list[str]:
    """A line for the masks picture when views are flagged ``surrounds_view``
    (:func:`robo3d.silhouettes.surrounding_views`: most masks reach all four sides of the
    image and cover most of it, the table and the room taken for the object), and whether
    the carve then made no hull: the picture said only "4 view(s) flagged by the mask
    check" over the table masked around a black bottle (random scene 711)."""
    sil = (metrics.get("stages") or {}).get("silhouettes") or {}
    views = [v.get("index", i) for i, v in enumerate(sil.get("views") or [])
             if isinstance(v, dict) and "surrounds_view" in ((v.get("qa") or {}).get("flags")
                                                              or [])]
    if not views:
        return []
    carve = (metrics.get("stages") or {}).get("carve") or {}
    hull = ("; no hull carved from them: the laser alone"
            if carve.get("empty") and "flagged as absurd" in str(carve.get("reason")) else "")
    return [f"{len(views)} view(s) flagged surrounds_view (masks over most of the image, on "
            f"all four sides: the surroundings taken for the object){hull}"]


def _laser_against_masks(metrics: Mapping[str, Any]) -> list[str]:
    """What the alignment's test of the laser points against the silhouettes said of the
    masks (``stages.align.outside_hull``), for the masks picture: a line when the masks
    as a whole contradict the laser (the alignment's warning sends the user to this
    picture), and the views it did not trust with the share of the points that each
    alone put outside. Without them the picture said "0 view(s) flagged" over masks that the
    laser showed to be wrong (a white checker bottle on a marker table: IoU 0.04-0.05,
    87 % of the laser's points outside them)."""
    oh = ((metrics.get("stages") or {}).get("align") or {}).get("outside_hull") or {}
    alone = {int(v["view"]): float(v["would_drop_alone_fraction"])
             for v in oh.get("views_not_used_contradict_laser") or []
             if isinstance(v, dict) and "view" in v
             and isinstance(v.get("would_drop_alone_fraction"), int | float)}
    notes = []
    if oh.get("contradicted"):
        frac = oh.get("would_drop_fraction")
        share = f"{100 * frac:.0f} % of" if isinstance(frac, int | float) else "many of"
        notes.append(f"the laser contradicts these masks: {share} its points lie outside "
                     "them, so none was dropped for it; the masks are likely wrong")
    agree = oh.get("views_agreement") or {}
    if agree.get("overrules") and isinstance(oh.get("dropped_fraction"), int | float):
        notes.append(f"the views agree (median IoU {agree.get('iou_median', 0):.2f} with the "
                     f"others' hull): {100 * oh['dropped_fraction']:.0f} % of the laser's "
                     "points lay outside them and were dropped as not on the object")
    if alone:
        views = ", ".join(f"{i} ({100 * f:.0f} %)" for i, f in sorted(alone.items())[:8])
        more = f" and {len(alone) - 8} more" if len(alone) > 8 else ""
        notes.append(f"views not trusted to drop laser points (the share that each alone "
                     f"put outside): {views}{more}")
    return notes


def _stripes(rec, stripes, n: int, tile: int) -> np.ndarray:
    from ..report import stripes_picture

    return stripes_picture(rec, stripes, n=max(1, (3 * n) // 4), tile_px=int(tile * 4 / 3))


def _tiles_row(tiles: list[np.ndarray]) -> np.ndarray:
    return np.concatenate(tiles, axis=1)


def _hull(path: str, metrics: Mapping[str, Any], up: np.ndarray, how: str,
          tile: int) -> np.ndarray:
    from ..meshio import read_mesh
    from ..report import mesh_views, titled

    V, F = read_mesh(path)
    carve = (metrics.get("stages") or {}).get("carve") or {}
    ev = metrics.get("evaluation") or {}
    lines = [f"{len(F)} faces; volume {carve['volume_m3'] * 1e6:.1f} cm3"
             if isinstance(carve.get("volume_m3"), int | float) else f"{len(F)} faces"]
    if isinstance(ev.get("hull_volume_iou"), int | float):
        lines[0] += f"; volume IoU with the true object {ev['hull_volume_iou']:.3f}"
    if carve.get("empty"):
        lines.append(f"no hull: {carve.get('reason', 'the silhouettes carved every voxel')}"
                     "; the scan's mesh is its measured surface")
    if isinstance((carve.get("pieces") or {}).get("warning"), str):
        lines.append(carve["pieces"]["warning"])
    lines.append(f"up: {how}")
    col = np.tile([0.55, 0.70, 0.85], (len(V), 1))
    return titled(_tiles_row(mesh_views(V, F, col, up, tile_px=tile)),
                  "Visual hull (carved from the silhouettes)", lines)


def _clouds(path: str, metrics: Mapping[str, Any], up: np.ndarray, tile: int) -> np.ndarray:
    from ..artefacts import load_clouds_npz
    from ..report import SWEEP_COLOURS, legend, points_views, titled

    clouds = load_clouds_npz(path)
    pts = np.concatenate([c.points_base for c in clouds]) if clouds else np.zeros((0, 3))
    nrm = np.concatenate([c.normals_base for c in clouds]) if clouds else np.zeros((0, 3))
    sweep = np.concatenate([np.full(len(c.points_base), k) for k, c in enumerate(clouds)]
                           ) if clouds else np.zeros(0, int)
    col = SWEEP_COLOURS[sweep % len(SWEEP_COLOURS)]
    row = _tiles_row(points_views(pts, col, up, normals=nrm, tile_px=tile))
    items = [(SWEEP_COLOURS[k % len(SWEEP_COLOURS)],
              f"sweep {c.sweep}: {len(c.points_base)} points") for k, c in enumerate(clouds)]
    lines = [f"{len(pts)} points in {len(clouds)} sweeps (at most 60,000 drawn)"]
    ev = metrics.get("evaluation") or {}
    acc = ev.get("aligned") or {}
    if isinstance(acc.get("median_mm"), int | float):
        lines.append(f"distance to the true surface: median {acc['median_mm']:.3f} mm, "
                     f"95th percentile {acc['p95_mm']:.3f} mm")
    return titled(np.concatenate([row, legend(items, row.shape[1])], axis=0),
                  "Aligned laser clouds, coloured by sweep", lines)


def _mesh(path: str, mesh: tuple[np.ndarray, np.ndarray], rec, metrics: Mapping[str, Any],
          cfg: Mapping[str, Any], up: np.ndarray, tile: int,
          tiles_out: list[np.ndarray]) -> np.ndarray:
    """The final mesh by its distance to the true surface when the recording carries
    one, else by each vertex's source (measured, hull, filled)."""
    from ..meshio import read_vertex_attributes
    from ..render import colormap
    from ..report import SOURCE_COLOURS, colour_bar, legend, mesh_views, source_colours, titled

    V, F = mesh
    truth = _truth(rec)
    m = (metrics.get("evaluation") or {}).get("mesh") or {}
    if truth is not None:
        vmax = float(cfg["evaluation"]["picture_vmax_mm"])
        col = colormap(truth.distance(V) * 1e3, vmax)
        foot = colour_bar(vmax, "mm from the true surface", 4 * tile)
        title = "Final mesh, coloured by its distance to the true surface"
        lines = [f"{len(F)} faces; median {m['median_mm']:.3f} mm, 95th percentile "
                 f"{m['p95_mm']:.3f} mm" if isinstance(m.get("median_mm"), int | float)
                 else f"{len(F)} faces"]
    else:
        attrs = read_vertex_attributes(path)
        source = np.asarray(attrs.get("source", np.zeros(len(V))), dtype=np.int64)
        col = source_colours(source)
        present = set(np.unique(np.clip(source, 0, max(SOURCE_COLOURS))).tolist())
        foot = legend([SOURCE_COLOURS[k] for k in sorted(SOURCE_COLOURS) if k in present],
                      4 * tile)
        title = "Final mesh, coloured by where its surface came from (no ground truth)"
        inf = (metrics.get("surface_sources") or {}).get("inferred_area_fraction")
        lines = [f"{len(F)} faces" + (f"; {100 * inf:.1f} % of its area inferred, not "
                                      "measured" if isinstance(inf, int | float) else "")]
    if (metrics.get("surface_sources") or {}).get("hull_contradicted"):
        lines.append("the visual hull contradicts the laser: nothing was closed from it, "
                     "the mesh is the measured surface")
    if (metrics.get("surface_sources") or {}).get("object_not_found"):
        lines.append("no object found (no box, no hull, too little above the table): the "
                     "mesh is what the laser saw, most likely the table")
    if (metrics.get("surface_sources") or {}).get("laser_unusable"):
        lines.append("the laser measured nothing usable on the object: the mesh is the "
                     "visual hull's, all of it inferred")
    tiles = mesh_views(V, F, col, up, tile_px=tile)
    tiles_out[:] = tiles[:1]
    return titled(np.concatenate([_tiles_row(tiles), foot], axis=0), title, lines)


def _truth(rec):
    """The recording's true surface, or None (none, or damaged: evaluate says which)."""
    from ..evaluate import TruthSurface
    from ..meshio import read_mesh

    data = rec.attachments.get("ground_truth/mesh.ply")
    if data is None:
        return None
    try:
        return TruthSurface(*read_mesh(data))
    except (Robo3dError, ValueError, RuntimeError, OSError):
        return None


def _timings(metrics: Mapping[str, Any]) -> np.ndarray:
    from ..report import timings_picture

    return timings_picture(metrics.get("timings") or {})


def _thumbnail(mesh_tiles: list[np.ndarray], metrics: Mapping[str, Any]) -> np.ndarray:
    """The first view of the final mesh picture, for the overview (which says what the
    colours mean)."""
    from ..report import placeholder

    if not mesh_tiles:
        return placeholder(f"no picture of {metrics.get('name', 'the mesh')}", 240)
    return mesh_tiles[0]

