"""The ``silhouettes`` stage: segment every silhouette view (seed §3.2) and keep its camera and
pose (:func:`robo3d.silhouettes.segment_view`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..artefacts import Silhouettes
from ..atomic import dir_mode, write_json
from ..errors import StageError
from .common import (
    Progress,
    log,
    log_image_camera,
    open_recording,
    reader_options,
    stage_threads,
    summary,
)

if TYPE_CHECKING:
    from ..silhouettes import SegmentOptions


# ---------------------------------------------------------------------------- stages
def stage_silhouettes(inputs: Mapping[str, str], outputs: Mapping[str, str],
                      cfg: Mapping[str, Any], rec_name: str,
                      has_laser: bool = False, threads: int | None = None
                      ) -> dict[str, Any]:
    """Segment every silhouette view (seed §3.2) and keep its camera and pose.

    Outputs: ``npz`` (:class:`robo3d.artefacts.Silhouettes`: masks, cameras, poses,
    ``qa_flagged`` per view), ``report`` (per view: threshold, area, components, whether
    the silhouette touches the ROI's or the image's border, the ROI, whether an
    empty-scene image was subtracted, where the background was sampled, whether GrabCut
    refined it, and ``qa``: ``flags`` of an absurd mask, see
    :func:`robo3d.silhouettes.silhouette_qa`; ``qa_flagged_views`` lists the flagged
    views), ``rrd`` (images with their masks at their cameras) and, when given,
    ``masks``: a folder of one PNG per view (``view_000.png``, 255 = silhouette).
    A view whose segmentation fails (empty, uniform, or covering its whole region) is
    named in a warning and flagged (``views_failed``, its QA flag ``segmentation failed:
    ...``) with an empty mask, which the carve leaves out. When more than half of the
    views fail (by the colour model: before the laser's points seed any mask, which they
    then do not), the segmentation is not trusted in this recording: in a scan with laser
    frames (``has_laser``, the rule's ``params.has_laser``) every view is then flagged
    with an empty mask (``silhouettes_failed`` in the report says why), the hull is
    empty and the laser's measurement goes on alone; without laser frames the stage
    fails with an error naming the first. An absurd mask is flagged, not dropped (so are
    most views' masks when they surround their views: ``surrounds_view``). ``threads``:
    views segmented side by side (the job's; the result does not depend on it)."""
    from ..silhouettes import SegmentOptions

    t0 = time.perf_counter()
    rec = open_recording(inputs["recording"], cfg, roles=("views",),
                         calibration=inputs.get("calibration"))
    views = sorted(rec.views, key=lambda m: m.timestamp_ns)
    cameras = [rec.camera_for(m) for m in views]
    poses = rec.camera_poses(views)
    options = SegmentOptions.from_config(cfg["segmentation"])
    ws = rec.workspace
    backgrounds = _background_images(inputs["recording"], cfg, views, cameras, poses,
                                     inputs.get("calibration"))
    masks, per_view, failed = [], [], {}
    progress = Progress("segmenting views", len(views))

    def one(i: int):
        try:
            return _segment_one(inputs["recording"], rec, i, views[i], cameras[i], poses[i],
                                backgrounds[i], ws, options)
        except StageError as exc:
            return exc

    # the views side by side (OpenCV and most of numpy release the GIL): the stage ran on
    # one core while the job held one, ahead of the stripes that wanted two
    with ThreadPoolExecutor(max_workers=stage_threads(threads)) as pool:
        for i, out in enumerate(pool.map(one, range(len(views)))):
            msg, cam = views[i], cameras[i]
            if isinstance(out, StageError):
                # one view that cannot be segmented (its object in the background's
                # colours) does not stop the others: an empty mask, flagged, unused
                failed[i] = str(out)
                log.warning("%s; the view is flagged and not used", out)
                reason = str(out).removeprefix(_where(inputs["recording"], i, msg) + ": ")
                out = np.zeros((cam.height, cam.width), bool), _failed_row(i, msg, reason)
            masks.append(out[0])
            per_view.append(out[1])
            progress(i + 1)
    given_up = None
    if views and len(failed) > len(views) // 2:
        what = (f"{len(failed)} of {len(views)} views could not be segmented (at most half "
                f"may fail); the first: {next(iter(failed.values()))}")
        if not has_laser:
            raise StageError(what)
        # random scene 182 of stop 36 (a black torus on a checker table, 2 of 3 views
        # failed) ended here although its laser sweeps were fine: the views that did
        # segment are not trusted either, and the laser's measurement goes on alone
        given_up = (f"{what}: no view is used; the scan goes on from the laser alone "
                    "(no hull, nothing closed from it)")
        log.warning("silhouettes: %s", given_up)
        for i, row in enumerate(per_view):
            if not row.get("failed"):
                masks[i] = np.zeros_like(masks[i])
                per_view[i] = _failed_row(
                    i, views[i], "most views of the recording could not be segmented")
    # the laser's points seed the masks of views the colour model got wrong, or found no
    # object in, when it segmented most views: not when it failed in most (random scene
    # 539 of stop 55, a black block on a dark-dotted table, 8 of 12 views failed: the
    # red laser measured its top alone, the masks seeded from it left the sides out, and
    # the hull they carved, a seventh of the block, closed 78 % of the mesh through it)
    laser_seeded = None
    if inputs.get("clouds") and cfg["segmentation"]["laser_reseed"]:
        laser_seeded = (
            {"checked": False, "why_not": "most views could not be segmented: the laser's "
             "points do not make the masks of a recording whose colour model failed"}
            if given_up is not None else
            _laser_reseed(inputs["recording"], inputs["clouds"], rec, views, cameras, poses,
                          ws, cfg, masks, per_view, backgrounds, options))
    resegmented = None
    if given_up is None and cfg["segmentation"]["resegment_spurious"]:
        resegmented = _resegment(inputs["recording"], rec, views, cameras, poses,
                                 backgrounds, ws, options, cfg, masks, per_view)
    _flag_surrounding(inputs["recording"], views, masks, per_view)
    report = _report(per_view, ws, t0)
    report["silhouettes_failed"] = given_up
    report["resegmented"] = resegmented
    report["laser_seeded"] = laser_seeded
    report["views_failed"] = [v["index"] for v in per_view if v.get("failed")]
    if rec.rectifiers:  # the views segmented as resampled to the pinhole camera
        report["rectified"] = {fid: r.describe() for fid, r in rec.rectifiers.items()}
    Silhouettes.from_views(masks, poses, [m.timestamp_ns for m in views], cameras,
                           [bool(v["qa"]["flags"]) for v in per_view], ws,
                           None if laser_seeded is None
                           else ["laser_seeded" in v for v in per_view]
                           ).save(outputs["npz"])
    if outputs.get("masks"):
        _write_mask_pngs(outputs["masks"], masks)
    _log_rerun(outputs["rrd"], rec_name, ws, views, cameras, poses, masks, report,
               int(cfg["rerun"]["max_images"]),
               decode=rec.decode if rec.rectifiers else None)
    write_json(outputs["report"], report)
    summary.info("segmented %d views in %.1f s; %d touch the image border, %d their region's",
             len(views), report["seconds"], report["n_touching_image_border"],
             report["n_touching_border"])
    return report


def _resegment(path: str, rec, views: list, cameras: list, poses: np.ndarray,
               backgrounds: list, ws, options: SegmentOptions, cfg: Mapping[str, Any],
               masks: list[np.ndarray], per_view: list[dict]) -> dict[str, Any]:
    """The views whose foreground the other views' hull rules out, segmented again inside
    its box (:func:`robo3d.silhouettes.resegment_spurious_views`); ``masks`` and
    ``per_view`` updated in place where the new mask is kept (its row then says
    ``resegmented``). Returns the check's report."""
    from ..silhouettes import resegment_spurious_views

    rows: dict[int, dict] = {}
    again = _segment_again(path, rec, views, cameras, poses, backgrounds, options, rows)
    new, rep = resegment_spurious_views(
        masks, cameras, poses, ws, again, carving_cfg=cfg["carving"],
        exclude=[i for i, r in enumerate(per_view) if r["qa"]["flags"]])
    for v, mask in new.items():
        log.warning("view %d (topic %s, t=%d ns): %.0f%% of its foreground lies outside the "
                    "other views' hull; segmented again inside that hull's box, %.0f%% "
                    "now", v, views[v].topic, views[v].timestamp_ns,
                    100 * rep["candidates"][v]["spurious_before"],
                    100 * rep["candidates"][v]["spurious_after"])
        masks[v] = mask
        per_view[v] = rows[v] | {"resegmented": {"box": rep["box"], **rep["candidates"][v]},
                                 "roi_source": "the other views' hull"}
    return rep


def _segment_again(path: str, rec, views: list, cameras: list, poses: np.ndarray,
                   backgrounds: list, options: SegmentOptions, rows: dict[int, dict]):
    """``again(view, box)``: the view segmented with ``box`` as its workspace (its report
    row into ``rows``), or None when that fails."""
    def again(v: int, box: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
        try:
            mask, rows[v] = _segment_one(path, rec, v, views[v], cameras[v], poses[v],
                                         backgrounds[v], box, options)
        except StageError:
            return None
        return mask

    return again


def _laser_reseed(path: str, clouds_path: str, rec, views: list, cameras: list,
                  poses: np.ndarray, ws, cfg: Mapping[str, Any], masks: list[np.ndarray],
                  per_view: list[dict], backgrounds: list,
                  options: SegmentOptions) -> dict[str, Any]:
    """The views whose masks the laser's points contradict, segmented again from where the
    laser measured the object (:func:`robo3d.silhouettes.resegment_laser_contradicted`,
    the points from :func:`robo3d.artefacts.object_points`); ``masks`` and ``per_view``
    updated in place where the new mask is kept (its row then says ``laser_seeded``, and
    a view whose segmentation had failed is no longer failed). Without a workspace box,
    first the views whose masks reach far beyond the laser's box of the object, segmented
    again inside it (:func:`_laser_box_reseed`). Returns the report."""
    from ..artefacts import load_clouds_npz, object_points
    from ..silhouettes import resegment_laser_contradicted, roi_from_box, silhouette_qa

    sc = cfg["segmentation"]
    points, frames, box, laser_ws = object_points(
        load_clouds_npz(clouds_path), cfg["triangulation"],
        box_margin=float(cfg["alignment"]["workspace_from_hull_margin"]))
    if len(points) < int(sc["laser_min_points"]):
        return {"checked": False, "points": int(len(points)),
                "why_not": f"{len(points)} laser points on the object (box: {box}): too few"}
    in_box = (_laser_box_reseed(path, rec, views, cameras, poses, laser_ws, cfg, masks,
                                per_view, backgrounds, options)
              if ws is None and laser_ws is not None else None)
    rois = []
    for i, row in enumerate(per_view):
        if row.get("roi") is not None:
            rois.append(tuple(row["roi"]))
        elif ws is not None:
            rois.append(roi_from_box(ws[0], ws[1], cameras[i], poses[i],
                                     margin_px=float(sc["roi_margin_px"])))
        else:
            rois.append(None)
    new, rep = resegment_laser_contradicted(
        masks, cameras, poses, points, frames, lambda v: rec.decode(views[v]), rois,
        max_outside=float(sc["laser_max_outside"]), tolerance_px=int(sc["laser_tolerance_px"]),
        min_points=int(sc["laser_min_points"]), band_px=int(sc["laser_band_px"]),
        min_area_ratio=float(sc["laser_min_area_ratio"]))
    for v, mask in new.items():
        cand = rep["candidates"][v]
        log.warning("view %d (topic %s, t=%d ns): %.0f%% of the laser's points on the object "
                    "lie outside its mask; segmented again from where the laser measured "
                    "the object, %.0f%% now", v, views[v].topic, views[v].timestamp_ns,
                    100 * cand["outside_before"], 100 * cand["outside_after"])
        masks[v] = mask
        row = {k: val for k, val in per_view[v].items() if k != "failed"}
        per_view[v] = row | {"area_px": int(np.count_nonzero(mask)), "roi": list(rois[v])
                             if rois[v] is not None else None,
                             "qa": silhouette_qa(mask, rois[v]), "laser_seeded": cand}
    return {"checked": True, "box": box, "within_laser_box": in_box, **rep}


def _laser_box_reseed(path: str, rec, views: list, cameras: list, poses: np.ndarray,
                      laser_ws: tuple[np.ndarray, np.ndarray], cfg: Mapping[str, Any],
                      masks: list[np.ndarray], per_view: list[dict], backgrounds: list,
                      options: SegmentOptions) -> dict[str, Any]:
    """A recording without a workspace box: the views more than ``carving.qa_max_spurious``
    of whose mask lies outside the laser's box of the object, segmented again with that
    box as their workspace (:func:`robo3d.silhouettes.resegment_outside_box`); ``masks``
    and ``per_view`` updated in place where the new mask is kept (its row then says
    ``within_laser_box``). Returns the report."""
    from ..silhouettes import resegment_outside_box

    rows: dict[int, dict] = {}
    again = _segment_again(path, rec, views, cameras, poses, backgrounds, options, rows)
    new, rep = resegment_outside_box(
        masks, cameras, poses, laser_ws, lambda v: again(v, laser_ws),
        max_outside=float(cfg["carving"]["qa_max_spurious"]),
        margin_px=float(cfg["segmentation"]["roi_margin_px"]))
    for v, mask in new.items():
        log.warning("view %d (topic %s, t=%d ns): %.0f%% of its mask lies outside the box of "
                    "the object the laser measured (the recording has no workspace box); "
                    "segmented again inside it, %.0f%% now", v, views[v].topic,
                    views[v].timestamp_ns, 100 * rep["candidates"][v]["outside_before"],
                    100 * rep["candidates"][v]["outside_after"])
        masks[v] = mask
        per_view[v] = rows[v] | {"within_laser_box": rep["candidates"][v],
                                 "roi_source": "the laser's box of the object"}
    return rep


def _segment_one(path: str, rec, i: int, msg, cam, T: np.ndarray,
                 background: np.ndarray | None, ws,
                 options: SegmentOptions) -> tuple[np.ndarray, dict]:
    """View ``i`` segmented (:func:`robo3d.silhouettes.segment_view`), warned about when
    cut off or absurd: its mask and its row of the report."""
    from ..silhouettes import segment_view

    image = rec.decode(msg)
    try:
        sil, roi_source = segment_view(image, cam, T, ws, background, options=options)
    except StageError as exc:
        raise StageError(f"{_where(path, i, msg)}: {exc}") from None
    if sil.touches_image_border:
        log.warning("view %d (topic %s, t=%d ns): the silhouette touches the image border, "
                    "the object is cut off in this view; with carving.outside_image=carve "
                    "this view carves the object's hidden part away", i, msg.topic,
                    msg.timestamp_ns)
    elif sil.touches_border:
        log.warning("view %d (topic %s, t=%d ns): the silhouette touches the border of its "
                    "region of interest (%s): the object may reach beyond it and be cut "
                    "off", i, msg.topic, msg.timestamp_ns, roi_source)
    if sil.qa["flags"]:
        log.warning("view %d (topic %s, t=%d ns): absurd silhouette, QA flags %s (fill "
                    "%.2f of its region, sides touched %s); flagged in the report and in "
                    "silhouettes.npz (qa_flagged)", i, msg.topic, msg.timestamp_ns,
                    ", ".join(sil.qa["flags"]), sil.qa["fill_fraction"],
                    ", ".join(sil.qa["sides_touched"]) or "none")
    row = {"index": i, "timestamp_ns": msg.timestamp_ns,
           "threshold": float(sil.threshold), "polarity": sil.polarity,
           "area_px": int(sil.area_px), "n_components": int(sil.n_components),
           "touches_border": bool(sil.touches_border),
           "touches_image_border": bool(sil.touches_image_border),
           "roi": [int(r) for r in sil.roi], "roi_source": roi_source,
           "centroid_uv": [float(c) for c in sil.centroid_uv],
           "background_subtracted": background is not None,
           "background_sample": sil.background_sample,
           "refined": sil.refined, "qa": sil.qa,
           "mask_png": f"view_{i:03d}.png"}
    return sil.mask, row


def _flag_surrounding(path: str, views: list, masks: list[np.ndarray],
                      per_view: list[dict]) -> None:
    """Flag ``surrounds_view`` in the views' rows (in place) where most masks surround their
    views (:func:`robo3d.silhouettes.surrounding_views`), with a warning."""
    from ..silhouettes import surrounding_views

    around = surrounding_views(masks)
    for i in around:
        qa = per_view[i].get("qa") or {}
        per_view[i]["qa"] = {**qa, "flags": [*qa.get("flags", []), "surrounds_view"]}
    if around:
        log.warning("%s: %d of %d views have masks that reach all four sides of the image "
                    "and cover most of it (views %s): the segmentation took the "
                    "surroundings (the table, the room) for the object; flagged "
                    "surrounds_view: they judge no laser point, and with laser frames carve "
                    "no hull alone", path, len(around), len(masks), around)


def _where(path: str, i: int, msg) -> str:
    """Where a view's message is: the file, its topic, its number and time."""
    return f"{path}: topic {msg.topic}, view {i} (t={msg.timestamp_ns} ns)"


def _failed_row(i: int, msg, reason: str) -> dict[str, Any]:
    """The report's row of view ``i`` whose segmentation failed for ``reason``:
    QA-flagged (``segmentation failed: ...``), an empty mask."""
    return {"index": i, "timestamp_ns": msg.timestamp_ns, "failed": reason,
            "threshold": None, "polarity": None, "area_px": 0, "n_components": 0,
            "touches_border": False, "touches_image_border": False, "roi": None,
            "roi_source": None, "centroid_uv": None, "background_subtracted": False,
            "background_sample": None, "refined": False,
            "qa": {"flags": [f"segmentation failed: {reason}"]},
            "mask_png": f"view_{i:03d}.png"}


def _report(per_view: list[dict], ws, t0: float) -> dict[str, Any]:
    """The stage's report from the views' rows."""
    return {"n_views": len(per_view), "views": per_view,
            "n_touching_border": sum(v["touches_border"] for v in per_view),
            "n_touching_image_border": sum(v["touches_image_border"] for v in per_view),
            "views_touching_image_border": [v["index"] for v in per_view
                                            if v["touches_image_border"]],
            "n_background_subtracted": sum(v["background_subtracted"] for v in per_view),
            "qa_flagged_views": [v["index"] for v in per_view if v["qa"]["flags"]],
            "n_qa_flagged": sum(bool(v["qa"]["flags"]) for v in per_view),
            "workspace_box": None if ws is None else [ws[0].tolist(), ws[1].tolist()],
            "seconds": round(time.perf_counter() - t0, 3)}


def _log_rerun(path: str, rec_name: str, ws, views: list, cameras: list, poses: np.ndarray,
               masks: list[np.ndarray], report: dict, max_images: int, decode=None) -> None:
    """The workspace box; a few evenly spaced views, each with its mask over it, at its
    camera as one entity (``base/silhouettes/camera``) along the ``view`` and ``time``
    timelines, so the viewer shows the current one; the report."""
    from ..viz import log_box, log_report, rerun_log, set_image_time, spaced_indices

    with rerun_log(path, rec_name) as rr_stream:
        if ws is not None:
            log_box(rr_stream, "base/silhouettes/workspace", ws[0], ws[1], label="workspace")
        for i in spaced_indices(len(views), max_images):
            set_image_time(rr_stream, views[i].timestamp_ns, view=int(i))
            log_image_camera(rr_stream, "base/silhouettes/camera", views[i], cameras[i],
                             poses[i], decode=decode, mask=masks[i], static=False)
        log_report(rr_stream, "reports/silhouettes", report)


def _write_mask_pngs(directory: str, masks: list[np.ndarray]) -> None:
    """One 8-bit PNG per view (255 = silhouette) into ``directory``, atomically: written
    into a temporary folder beside it, which then replaces it."""
    import shutil
    import tempfile

    import cv2

    target = Path(directory)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", dir=target.parent))
    os.chmod(tmp, dir_mode())  # mkdtemp makes 0700: others of the cell must read the masks
    try:
        for i, m in enumerate(masks):
            if not cv2.imwrite(str(tmp / f"view_{i:03d}.png"), m.astype(np.uint8) * 255):
                raise StageError(f"could not write mask PNG {tmp / f'view_{i:03d}.png'}")
        if target.exists():
            shutil.rmtree(target)
        tmp.rename(target)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _background_images(path: str, cfg: Mapping[str, Any], views: list, cameras: list,
                       poses: np.ndarray, calibration: str | None = None
                       ) -> list[np.ndarray | None]:
    """For each view, the decoded empty-scene image of ``segmentation.background_topic``
    taken nearest its pose (same camera), or None when there is none close enough. Their
    poses use the views' calibration (``calibration``: the scan's calibration file)."""
    from dataclasses import replace

    from ..transforms import rotation_angle_deg

    seg = cfg["segmentation"]
    out: list[np.ndarray | None] = [None] * len(views)
    topic = seg.get("background_topic")
    if not topic or not views:
        return out
    from ..recording.reader import read_recording

    options = reader_options(cfg)
    options["topics"] = replace(options["topics"], views=topic)
    rec = read_recording(path, roles=("views",), require=False, **options)
    if calibration:
        from ..calibration.io import apply_calibration

        rec = apply_calibration(rec, calibration)
    bgs = [m for m in rec.views if m.topic == topic]
    if not bgs:
        log.warning("segmentation.background_topic %s has no images in %s: segmenting "
                    "without background subtraction", topic, path)
        return out
    bg_poses = rec.camera_poses(bgs)
    max_mm, max_deg = seg["background_max_offset_mm"], seg["background_max_offset_deg"]
    decoded: dict[int, np.ndarray] = {}
    for i, (cam, T) in enumerate(zip(cameras, poses, strict=True)):
        best, best_d = None, np.inf
        for j, (msg, Tb) in enumerate(zip(bgs, bg_poses, strict=True)):
            if msg.frame_id != cam.frame_id:
                continue
            d_mm = float(np.linalg.norm(Tb[:3, 3] - T[:3, 3])) * 1e3
            d_deg = float(rotation_angle_deg(Tb[:3, :3].T @ T[:3, :3]))
            if d_mm <= max_mm and d_deg <= max_deg and d_mm + d_deg < best_d:
                best, best_d = j, d_mm + d_deg
        if best is None:
            log.warning("view %d (t=%d ns): no empty-scene image on %s within %.2f mm and "
                        "%.2f deg of its pose: segmented without background subtraction", i,
                        views[i].timestamp_ns, topic, max_mm, max_deg)
            continue
        if best not in decoded:
            decoded[best] = rec.decode(bgs[best])
        out[i] = decoded[best]
    return out
