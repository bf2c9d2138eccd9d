"""The report's pictures and overview (robo3d.report, robo3d.overview, the pictures
stage): the up axis found from the cameras (a y-up scene drawn upright), the overlays on
small synthetic images, the point splatting's z-buffer, the mesh coloured by source
(not by an error colour bar) without ground truth, and figures and columns named in
words with their units and targets. Fast: small images, no workflow run."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from robo3d.report import (
    SOURCE_COLOURS,
    find_up,
    mask_overlay,
    placeholder,
    source_colours,
    stripe_overlay,
    timings_picture,
)

#: +z -> +y: the rotation that turns a z-up scene into a y-up one (x stays).
Z_TO_Y = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _dome(n: int = 24, elevation_deg: float = 40.0, r: float = 0.4,
          azimuths_deg: tuple[float, float] = (0.0, 360.0)) -> np.ndarray:
    """Camera centres on a ring above the origin (z up), as a robot places them."""
    full = azimuths_deg[1] - azimuths_deg[0] >= 360
    a = np.radians(np.linspace(*azimuths_deg, n, endpoint=not full))
    e = np.radians(elevation_deg)
    return r * np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a),
                         np.full(n, np.sin(e))], axis=1)


def _looking_at_origin(centres: np.ndarray, roll_deg: np.ndarray | float = 0.0,
                       up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_base_camera (N, 4, 4) of cameras at ``centres`` looking at the origin (camera z
    forward, y down), level (image rows horizontal about ``up``), then rolled."""
    f = -centres / np.linalg.norm(centres, axis=1, keepdims=True)
    x = np.cross(f, np.asarray(up))
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(f, x)
    r = np.radians(np.broadcast_to(roll_deg, (len(f),)))[:, None]
    x, y = np.cos(r) * x + np.sin(r) * y, -np.sin(r) * x + np.cos(r) * y
    T = np.tile(np.eye(4), (len(f), 1, 1))
    T[:, :3, 0], T[:, :3, 1], T[:, :3, 2], T[:, :3, 3] = x, y, f, centres
    return T


def _turned(T: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Poses ``T`` in a frame turned by ``R`` (positions and orientations)."""
    out = T.copy()
    out[:, :3, :3] = R @ T[:, :3, :3]
    out[:, :3, 3] = T[:, :3, 3] @ R.T
    return out


def _capped_cylinder():
    """A cylinder (z from 0 to 0.06 m) whose top half is red, the rest grey."""
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_cylinder(radius=0.02, height=0.06, resolution=24,
                                                  split=6)
    v = np.asarray(m.vertices) + [0, 0, 0.03]
    col = np.where((v[:, 2] > 0.03)[:, None], [1.0, 0.0, 0.0], [0.7, 0.7, 0.7])
    return v, np.asarray(m.triangles), col


# ------------------------------------------------------------------------- up axis
def test_up_from_level_cameras_in_a_z_up_and_a_y_up_scene():
    T = _looking_at_origin(_dome())
    up, how = find_up(np.zeros(3), [T])
    assert np.allclose(up, [0, 0, 1]) and how == ("normal to the cameras' level image rows, "
                                                  "snapped to +z")
    up_y, how_y = find_up(np.zeros(3), [_turned(T, Z_TO_Y)])
    assert np.allclose(up_y, [0, 1, 0]) and "snapped to +y" in how_y


def test_up_of_a_cap_of_views_in_front_comes_from_the_level_rows_not_the_mean():
    """A robot's views from one side only (azimuths -60..60 degrees, 40 degrees up, as
    DTU's), in a frame turned by 35 degrees (not snapped): the level image rows give up
    within a degree; the cameras' mean direction would lean 40 degrees toward them."""
    lean = np.array([[1, 0, 0], [0, np.cos(0.61), -np.sin(0.61)],
                     [0, np.sin(0.61), np.cos(0.61)]])
    cap = _dome(12, 40.0, azimuths_deg=(-60.0, 60.0))
    T = _turned(_looking_at_origin(cap), lean)
    up, how = find_up(np.zeros(3), [T])
    assert np.degrees(np.arccos(np.clip(up @ lean[:, 2], -1, 1))) < 1.0
    assert how == "normal to the cameras' level image rows"
    mean = T[:, :3, 3].mean(axis=0)
    assert np.degrees(np.arccos(mean @ lean[:, 2] / np.linalg.norm(mean))) > 30


def test_up_from_columns_a_ring_and_without_cameras():
    # a camera turned a quarter (the Middlebury temple's): its columns are level
    T = _turned(_looking_at_origin(_dome(16, 20.0), roll_deg=90.0), Z_TO_Y)
    up, how = find_up(np.zeros(3), [T])
    assert np.allclose(up, [0, 1, 0]) and "level image columns" in how
    # a ring level with the object, every view rolled at random: the ring's axis
    rolls = np.random.default_rng(1).uniform(-180, 180, 24)
    ring = _dome(24, 0.0) + [0, 0, 0.005]
    up, how = find_up(np.zeros(3), [_turned(_looking_at_origin(ring, rolls), Z_TO_Y)])
    assert np.allclose(up, [0, 1, 0]) and "ring" in how
    # views above, all turned alike (no plane of rows): their mean direction
    T = _looking_at_origin(_dome(8, 60.0))
    T[:, :3, :3] = T[0, :3, :3]
    up, how = find_up(np.zeros(3), [T])
    assert np.allclose(up, [0, 0, 1]) and "mean direction" in how
    up0, how0 = find_up(np.zeros(3), [])
    assert np.allclose(up0, [0, 0, 1]) and "no cameras" in how0


def test_a_y_up_object_is_drawn_upright_with_the_found_up():
    """The cylinder turned so that +y is up: rendered about the up found from its
    cameras, its red top is at the top of the picture; about z (the old fixed choice)
    it lies on its side (red and grey side by side, not above each other)."""
    from robo3d.render import render_mesh

    v, f, col = _capped_cylinder()
    v_y = v @ Z_TO_Y.T
    up, _ = find_up(v_y.mean(axis=0), [_turned(_looking_at_origin(_dome()), Z_TO_Y)])

    def rows_cols(img):
        red = (img[:, :, 0] > 120) & (img[:, :, 1] < 60)
        grey = (np.abs(img[:, :, 0].astype(int) - img[:, :, 1]) < 8) & (img[:, :, 0] < 230)
        return (np.nonzero(red)[0].mean(), np.nonzero(grey)[0].mean(),
                np.nonzero(red)[1].mean(), np.nonzero(grey)[1].mean())

    r_red, r_grey, _, _ = rows_cols(render_mesh(v_y, f, vertex_colors=col, up=up,
                                                elevation_deg=10, width=96, height=96))
    assert r_red < r_grey - 10  # red above grey
    r_red2, r_grey2, c_red2, c_grey2 = rows_cols(render_mesh(v_y, f, vertex_colors=col,
                                                             elevation_deg=10, width=96,
                                                             height=96))
    assert abs(r_red2 - r_grey2) < 6 and abs(c_red2 - c_grey2) > 10  # on its side
    # z up keeps the pictures of before: the default and up=+z are the same image
    assert np.array_equal(render_mesh(v, f, width=32, height=24),
                          render_mesh(v, f, width=32, height=24, up=np.array([0, 0, 2.0])))


# ------------------------------------------------------------------------- overlays
def test_mask_overlay_outlines_the_mask_and_dims_the_background():
    img = np.full((40, 60), 200, np.uint8)
    mask = np.zeros((40, 60), bool)
    mask[10:30, 20:40] = True
    out = mask_overlay(img, mask, colour=(0, 190, 255))
    assert out.shape == (40, 60, 3) and out.dtype == np.uint8
    assert tuple(out[10, 25]) == (0, 190, 255) and tuple(out[20, 20]) == (0, 190, 255)
    assert out[20, 30].mean() > out[0, 0].mean() + 50  # inside brighter than the outside
    assert out[0, 0, 0] == round(200 * 0.55)
    half = mask_overlay(img.astype(np.uint16) * 100, mask, width=30)  # 16-bit, resized
    assert half.shape == (20, 30, 3)
    with pytest.raises(ValueError, match="mask must be"):
        mask_overlay(img, mask[:, :10])


def test_stripe_overlay_marks_each_centre_at_its_scaled_pixel():
    img = np.zeros((50, 80, 3), np.uint8)
    img[25, :] = 180  # the laser line
    u = np.array([10.2, 40.7, 79.9])
    v = np.array([25.0, 25.4, 25.0])
    out = stripe_overlay(img, u, v, colour=(0, 230, 90))
    for x, y in zip(u.astype(int), v.astype(int), strict=True):
        assert tuple(out[y, x]) == (0, 230, 90)
    assert np.count_nonzero(np.all(out == (0, 230, 90), axis=2)) <= 4 * 3
    assert out[25, 60, 0] > 180  # the uncovered line is brightened, not hidden
    small = stripe_overlay(img, u, v, width=40)
    assert small.shape == (25, 40, 3) and tuple(small[12, 5]) == (0, 230, 90)
    with pytest.raises(ValueError, match="same length"):
        stripe_overlay(img, u, v[:2])


def test_render_points_nearest_point_wins_its_pixel():
    from robo3d.render import render_points

    # two points on the camera's line of sight (looking down from +z, elevation 90)
    pts = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.01], [0.02, 0.02, 0.0], [-0.02, -0.02, 0.0]])
    col = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0], [0, 1.0, 0]])
    img = render_points(pts, col, azimuth_deg=0, elevation_deg=90, width=41, height=41,
                        splat_px=1)
    centre = img[19:22, 19:22].reshape(-1, 3)
    assert any(tuple(c) == (0, 0, 255) for c in centre)  # the nearer, blue
    assert not any(tuple(c) == (255, 0, 0) for c in centre)  # the hidden red
    assert np.array_equal(img, render_points(pts, col, azimuth_deg=0, elevation_deg=90,
                                             width=41, height=41, splat_px=1))
    assert np.all(render_points(pts[:0], col[:0], width=16, height=16) == 255)


def test_pictures_that_say_why_and_the_timings_bars():
    p = placeholder("no laser frames in this recording")
    assert p.shape[0] == 60 and p.dtype == np.uint8
    t = timings_picture({"carve": {"seconds": 7.7, "max_rss_mb": 344.0},
                         "fuse": {"seconds": 2.0, "max_rss_mb": None}, "total_seconds": 9.7})
    assert t.shape[1] == 720 and t.shape[0] > 60
    assert timings_picture({}).shape[0] == 60


# ------------------------------------------------------------------------- final mesh
def test_without_ground_truth_the_mesh_is_coloured_by_source_not_by_error(tmp_path):
    """No ground truth: every drawn vertex colour is one of the source colours, and the
    error ramp's colours (its blue end) appear nowhere: no error colour bar."""
    import open3d as o3d

    from robo3d.meshio import write_mesh
    from robo3d.render import colormap
    from robo3d.stages.pictures import _mesh

    m = o3d.geometry.TriangleMesh.create_sphere(0.03, resolution=12)
    v, f = np.asarray(m.vertices), np.asarray(m.triangles)
    source = (v[:, 2] < -0.01).astype(np.uint8)  # the bottom inferred from the hull
    write_mesh(tmp_path / "mesh.ply", v, f, attributes={"source": source})
    cols = source_colours(source)
    assert np.allclose(cols[source == 0], SOURCE_COLOURS[0][0])
    assert np.allclose(cols[source == 1], SOURCE_COLOURS[1][0])
    rec = SimpleNamespace(attachments={})
    metrics = {"surface_sources": {"inferred_area_fraction": 0.2}}
    tiles: list[np.ndarray] = []
    img = _mesh(str(tmp_path / "mesh.ply"), (v, f), rec, metrics,
                {"evaluation": {"picture_vmax_mm": 0.2}}, np.array([0, 0, 1.0]), 64, tiles)
    blue_end = (colormap(np.zeros(1), 0.2)[0] * 255).round().astype(int)
    assert not np.any(np.all(np.abs(img.astype(int) - blue_end) <= 2, axis=2))
    orange = (np.array(SOURCE_COLOURS[1][0]) * 255).round().astype(int)
    assert np.any(np.all(np.abs(img.astype(int) - orange) <= 2, axis=2))  # legend swatch
    assert len(tiles) == 1 and tiles[0].shape == (48, 64, 3)


# ------------------------------------------------------------------------- overview
def _metrics(truth: bool) -> dict:
    m = {"name": "scan_a", "skipped": {}, "timings": {
        "carve": {"seconds": 7.0, "max_rss_mb": 300.0}, "total_seconds": 40.0},
        "surface_sources": {"mesh": {"measured": 0.8}}}
    if truth:
        m["evaluation"] = {"mask_iou": {"mean": 0.99, "min": 0.9},
                           "mesh": {"median_mm": 0.02, "p95_mm": 0.3,
                                    "completeness": {"within_mm": {"0.5": 0.995}}},
                           "poses": {"worst_after_obj_mm": 0.04, "worst_after_deg": 0.01}}
    else:
        m["skipped"]["evaluation"] = "the recording carries no ground truth"
    return m


def test_key_figures_against_their_targets_and_the_status():
    from robo3d.overview import key_figures, recording_status

    figs = {f["label"]: f for f in key_figures(_metrics(True))}
    worst = figs["Mask IoU, worst view"]
    assert worst["met"] is False and worst["target"] == "≥ 0.93"
    p95 = figs["Final mesh to the true surface, 95th percentile"]
    assert p95["met"] is False and p95["unit"] == "mm"
    cover = figs["True surface covered by the mesh within 0.5 mm"]
    assert cover["value"] == pytest.approx(99.5) and cover["unit"] == "%" and cover["met"]
    assert figs["Time of all stages (job time, one core each)"]["met"] is True
    status, _ = recording_status(_metrics(True))
    assert status == "done; 2 of 8 targets missed"
    status, notes = recording_status(_metrics(False))
    assert "no ground truth" in status and notes == []
    masks_only = {**_metrics(True), "skipped": {"surface_evaluation": "no ground_truth/mesh.ply"}}
    del masks_only["evaluation"]["mesh"]
    status, notes = recording_status(masks_only)  # true silhouettes, no true surface
    assert "no true surface" in status and notes == ["surface_evaluation: no ground_truth/"
                                                     "mesh.ply"]
    judged = [f["label"] for f in key_figures(_metrics(False)) if f["met"] is not None]
    assert judged == ["Time of all stages (job time, one core each)"]  # no truth: no error
    # silhouettes that failed: named in the notes, beside the figures
    failed = _metrics(False)
    failed["stages"] = {"silhouettes": {"views_failed": [1, 4]}, "carve": {"empty": True},
                        "align": {"outside_hull": {"contradicted": True}}}
    failed["surface_sources"] = {"hull_contradicted": True}
    _, notes = recording_status(failed)
    assert notes == ["2 view(s) gave no silhouette and were not used",
                     "no visual hull: the silhouettes carved every voxel",
                     "the silhouettes contradict the laser: no laser point was dropped by them",
                     "the hull contradicts the laser: nothing closed, the mesh is the "
                     "measured surface"]
    # the carve's own reason when it gives one (random scene 711: only flagged views)
    failed["stages"]["carve"]["reason"] = "every view left to carve (4) has a silhouette ..."
    assert recording_status(failed)[1][1] == ("no visual hull: every view left to carve (4) "
                                              "has a silhouette ...")


def test_a_scan_where_nothing_locates_the_object_says_so():
    """No workspace box, no hull, and the laser's points on the table with too few above
    it (random scene 688: a black bracket the red laser did not show): the mesh is the
    table's, and metrics.json, the overview and the summary say that no object was
    found, not only the logs."""
    from robo3d.overview import recording_status
    from robo3d.stages.evaluate import _object_not_found

    align = {"workspace_from_hull": {
        "skipped": "the hull is empty",
        "laser": {"skipped": "too few laser points above the table to find the object",
                  "object_found": False}}}
    why = _object_not_found(align)
    assert why.startswith("no object found") and "the hull is empty" in why
    assert "most likely the table" in why
    # the hull's box, or the laser's, or a recording's own box: the object is located
    assert _object_not_found({"workspace_from_hull": {"box_min": [0, 0, 0]}}) is None
    assert _object_not_found({"workspace_from_hull": {
        "skipped": "no views", "laser": {"box_min": [0, 0, 0]}}}) is None
    assert _object_not_found({}) is None and _object_not_found(None) is None
    m = _metrics(False)
    m["surface_sources"] = {"object_not_found": why}
    _, notes = recording_status(m)
    assert any(n.startswith("no object found") for n in notes)


def test_a_scan_whose_laser_measured_nothing_says_its_mesh_is_the_hull():
    """The fuse stage meshes the views' hull when the laser measured nothing usable on
    the object (random scene 1163); the overview says so, not only reports/fuse.json."""
    from robo3d.overview import recording_status

    m = _metrics(False)
    _, before = recording_status(m)
    assert not any("nothing usable" in n for n in before)
    m["surface_sources"] = {"laser_unusable": "TSDF fusion: no point is usable"}
    _, notes = recording_status(m)
    assert any(n.startswith("the laser measured nothing usable on the object") and
               "all of it inferred" in n for n in notes), notes


def test_overview_and_batch_table_speak_in_words_with_units(tmp_path):
    import json

    from robo3d.evaluate import batch_rows
    from robo3d.overview import batch_html, overview_html, write_batch_report

    ms = [_metrics(True), {**_metrics(False), "name": "real_b"}]
    page = batch_html(batch_rows(ms))
    header = page.split("<table>")[1].split("</tr><tr><td>")[0]
    assert "distance, median (mm)" in header and "true surface covered within 0.5 mm (%)" \
        in header
    assert "mesh_median_mm" not in page and "_s<" not in page  # no machine keys
    assert "7.0 s<br>300 MB" in page  # time and memory, apart, with units
    ov = overview_html(ms, [None, b"\x89PNG"], vmax_mm=0.2)
    assert "<h2>scan_a</h2>" in ov and "≥ 0.97" in ov and "missed" in ov
    assert "No ground truth: coloured by where the surface came from" in ov
    assert "data:image/png;base64," in ov
    paths = []
    for k, m in enumerate(ms):
        paths.append(tmp_path / f"m{k}.json")
        paths[-1].write_text(json.dumps(m))
    write_batch_report([str(p) for p in paths], [str(tmp_path / "none.png")] * 2,
                       str(tmp_path / "b.tsv"), str(tmp_path / "b.html"),
                       str(tmp_path / "o.html"))
    assert (tmp_path / "b.tsv").read_text().startswith("recording\thull_iou")
    assert "<h2>real_b</h2>" in (tmp_path / "o.html").read_text()
    with pytest.raises(ValueError, match="one picture per recording"):
        write_batch_report([str(paths[0])], [], "x", "y", "z")


def test_the_masks_picture_says_when_the_masks_took_the_surroundings():
    from robo3d.stages.pictures import _surroundings

    views = [{"index": i, "qa": {"flags": ["surrounds_view"] if i < 3 else []}}
             for i in range(4)]
    carve = {"empty": True, "reason": "every view left to carve (3) has a silhouette the "
             "segmentation flagged as absurd (view 0: segmentation: surrounds_view)"}
    line, = _surroundings({"stages": {"silhouettes": {"views": views}, "carve": carve}})
    assert line.startswith("3 view(s) flagged surrounds_view") and "no hull" in line
    line, = _surroundings({"stages": {"silhouettes": {"views": views}}})
    assert "no hull" not in line
    assert _surroundings({"stages": {"silhouettes": {"views": views[3:]}}}) == []
    assert _surroundings({}) == []


def test_the_masks_picture_says_when_the_laser_contradicts_the_masks():
    """The alignment's warning on masks that the laser contradicts sends the user to
    pictures/masks.png, which said only "0 view(s) flagged by the mask check" (random
    scene 408: a white checker bottle on a marker table, masks IoU 0.04-0.05)."""
    from robo3d.overview import recording_status
    from robo3d.stages.pictures import _laser_against_masks

    oh = {"contradicted": True, "would_drop_fraction": 0.8702,
          "views_not_used_contradict_laser": [{"view": 0, "would_drop_alone_fraction": 0.1174}]}
    lines = _laser_against_masks({"stages": {"align": {"outside_hull": oh}}})
    assert len(lines) == 2
    assert "contradicts these masks: 87 % of its points" in lines[0]
    assert lines[1].endswith(": 0 (12 %)")
    many = {"views_not_used_contradict_laser": [
        {"view": i, "would_drop_alone_fraction": 0.3} for i in range(11)]}
    only = _laser_against_masks({"stages": {"align": {"outside_hull": many}}})
    assert len(only) == 1 and only[0].endswith("7 (30 %) and 3 more")
    ok = {"contradicted": False, "would_drop_fraction": 0.01,
          "views_not_used_contradict_laser": []}
    assert _laser_against_masks({"stages": {"align": {"outside_hull": ok}}}) == []
    assert _laser_against_masks({}) == []
    # views that agree overrule the laser (random scene 379): the picture says so
    over = {"dropped_fraction": 0.92, "views_agreement": {"overrules": True,
                                                          "iou_median": 0.8368}}
    line, = _laser_against_masks({"stages": {"align": {"outside_hull": over}}})
    assert "views agree (median IoU 0.84" in line and "92 % of the laser's points" in line
    status, notes = recording_status({**_metrics(False), "stages": {
        "align": {"outside_hull": over}}})
    assert notes[-1] == ("the views agree with each other and overrule the laser: 92 % of "
                         "its points outside them dropped as not on the object")


def test_the_laser_colour_check_is_in_the_overview_where_it_matters():
    """A laser colour changed from the frames' vote (by the views, or by motion without
    them) is said in the overview, and so is a close colour that nothing could check:
    its points may be a texture's edges, measured surface in every file."""
    from robo3d.overview import recording_status

    def notes(check):
        m = _metrics(False)
        m["stages"] = {"stripes": {"laser_colour": (check or {}).get("colour", "red"),
                                   "laser_colour_check": check}}
        return [n for n in recording_status(m)[1] if n.startswith("laser colour")]

    assert notes(None) == []
    by_motion = {"contested": True, "colour_by_laser_frames": "red", "colour": "blue",
                 "skipped": "no views in the recording",
                 "motion": {"pairs": 24, "contrasts": {
                     "red": {"moves_with": "scene"}, "blue": {"moves_with": "camera"}}}}
    (n,) = notes(by_motion)
    assert n.startswith("laser colour blue, not the laser frames' vote red") and "motion" in n
    by_views = {"contested": True, "colour_by_laser_frames": "red", "colour": "blue",
                "views": 6, "excess": {"red": -247.0, "blue": 551.0}}
    (n,) = notes(by_views)
    assert "told by the views" in n
    # kept and confirmed, by the views or by motion: nothing to say
    assert notes({**by_views, "colour": "red"}) == []
    confirmed = {**by_motion, "colour": "red", "motion": {"pairs": 24, "contrasts": {
        "red": {"moves_with": "camera"}, "blue": {"moves_with": None}}}}
    assert notes(confirmed) == []
    # close, and neither the views nor the motion could tell
    unchecked = {**confirmed, "motion": {"pairs": 3, "contrasts": {
        "red": {"moves_with": None}, "blue": {"moves_with": None}}}}
    (n,) = notes(unchecked)
    assert n.startswith("laser colour red was close to another and could not be checked")
    assert "no views in the recording" in n and "texture" in n
    # laser-off frames subtracted: the scene's texture is gone, the vote stands on them
    assert notes({"contested": True, "colour_by_laser_frames": "red", "colour": "red",
                  "skipped": "laser-off frames subtracted: the scene is already taken "
                             "away"}) == []
