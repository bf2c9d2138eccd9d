"""A scan whose laser measured too little of the object for a surface, with no views to
close it (random scene 844: a black thin wall under a green laser, a monochrome camera,
48 points on the object in 40 frames): the fuse stage fails with an error that says what
was measured and what to do, and writes nothing."""

from __future__ import annotations

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
