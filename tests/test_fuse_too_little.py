"""A scan whose laser measured too little of the object for a surface, with no views to
close it (random scene 844: a black thin wall under a green laser, a monochrome camera,
48 points on the object in 40 frames): the fuse stage fails with an error that says what
was measured and what to do, and writes nothing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from robo3d.artefacts import SweepCloud, save_clouds_npz
from robo3d.config import default_config
from robo3d.errors import StageError
from robo3d.pipeline import stage_fuse


def _sparse_clouds() -> list[SweepCloud]:
    """Three frames five apart (those between found no stripe), two points each 20 mm
    apart, on a wall facing the sensor 0.3 m away: a stripe found here and there on a
    dark object."""
    rows = []
    for f in (0, 5, 10):
        for k in range(2):
            rows.append((f, 30 * k, np.array([0.02 * k, 0.0, 0.02 + 0.001 * f])))
    p = np.array([r[2] for r in rows])
    origin = np.array([0.0, -0.3, 0.05])
    n = origin - p
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    box = [[-0.05, -0.05, 0.0], [0.05, 0.05, 0.1]]
    return [SweepCloud(points_base=p, normals_base=n,
                       frame_index=np.array([r[0] for r in rows], np.int64),
                       confidence=np.ones(len(p)), sweep=0,
                       sensor_origin_base=np.repeat(origin[None], len(p), axis=0),
                       report={"workspace": box},
                       line=np.array([100 + 20 * r[1] for r in rows], np.int64),
                       line_axis=np.zeros(len(p), np.uint8))]


def test_too_little_measured_and_no_hull_is_a_clear_error(tmp_path):
    save_clouds_npz(tmp_path / "aligned.npz", _sparse_clouds())
    outs = {"ply": str(tmp_path / "fused.ply"), "measured": str(tmp_path / "measured.ply"),
            "report": str(tmp_path / "reports" / "fuse.json"),
            "rrd": str(tmp_path / "fuse.rrd")}
    with pytest.raises(StageError) as err:
        stage_fuse({"aligned": str(tmp_path / "aligned.npz")}, outs, default_config(), "r")
    msg = str(err.value)
    assert "empty mesh from laser" in msg
    assert "6 laser points on the object from 3 frames of 1 sweep(s)" in msg, msg
    assert "no visual hull (no views)" in msg and "aligned.ply" in msg
    assert not any((tmp_path / p).exists() for p in ("fused.ply", "measured.ply",
                                                     "reports/fuse.json", "fuse.rrd"))


def _empty_clouds() -> list[SweepCloud]:
    """One sweep whose every point the workspace crop dropped: the laser's line lay on
    the table beside the object (random scene 1163: one sweep of a thin wall)."""
    z3, z = np.zeros((0, 3)), np.zeros(0, np.int64)
    return [SweepCloud(points_base=z3, normals_base=z3, frame_index=z,
                       confidence=np.zeros(0), sweep=0, sensor_origin_base=z3,
                       report={"workspace": [[-0.05, -0.05, 0.0], [0.05, 0.05, 0.1]]},
                       line=z, line_axis=np.zeros(0, np.uint8))]


def test_nothing_measured_on_the_object_gives_the_hull_labelled_inferred(tmp_path):
    """With views, a scan whose laser measured nothing usable on the object delivers the
    views' hull as its surface, every vertex labelled inferred, and an empty measured
    surface; without views it is a clear error naming what was missing."""
    import json

    from robo3d.carving import make_grid
    from robo3d.errors import NoUsablePoints
    from robo3d.fusion import HULL
    from robo3d.meshio import read_mesh, read_vertex_attributes

    save_clouds_npz(tmp_path / "aligned.npz", _empty_clouds())
    grid = make_grid(np.array([-0.03, -0.03, 0.0]), np.array([0.03, 0.03, 0.06]),
                     resolution=40)
    ax = [grid.origin[i] + grid.voxel_size * np.arange(grid.shape[i]) for i in range(3)]
    X, Y, Z = np.meshgrid(*ax, indexing="ij")
    grid.occupancy[...] = (X ** 2 + Y ** 2 + (Z - 0.03) ** 2) <= 0.02 ** 2
    grid.save_npz(tmp_path / "hull.npz")
    outs = {"ply": str(tmp_path / "fused.ply"), "measured": str(tmp_path / "measured.ply"),
            "report": str(tmp_path / "reports" / "fuse.json"),
            "rrd": str(tmp_path / "fuse.rrd")}
    rep = stage_fuse({"aligned": str(tmp_path / "aligned.npz"),
                      "hull": str(tmp_path / "hull.npz")}, outs, default_config(), "r")
    assert rep["source"] == "visual hull" and rep["method"] == "hull"
    assert "no point is usable" in rep["laser_unusable"]
    assert rep["inferred_area_fraction"] == 1.0 and rep["measured_faces"] == 0
    V, F = read_mesh(outs["ply"])
    assert len(F) > 100 and np.all(read_vertex_attributes(outs["ply"])["source"] == HULL)
    # the hull's surface: a sphere of 20 mm about (0, 0, 30 mm), to a voxel (1.5 mm)
    r = np.linalg.norm(V - [0.0, 0.0, 0.03], axis=1)
    assert np.all(np.abs(r - 0.02) < 0.0025), (r.min(), r.max())
    assert json.loads((tmp_path / "reports" / "fuse.json").read_text())["note"].startswith(
        "the laser measured nothing usable")
    # without views: the error says no point was usable, and nothing is written
    for p in outs.values():
        Path(p).unlink(missing_ok=True)
    with pytest.raises(NoUsablePoints, match="no point is usable"):
        stage_fuse({"aligned": str(tmp_path / "aligned.npz")}, outs, default_config(), "r")
    assert not any(Path(p).exists() for p in outs.values())
