"""The workflow's stages run in process on one recording, for tests that need a scan's
intermediate files without Snakemake (``tests/test_view.py``, ``tests/test_table.py``,
``tests/test_clock_offset.py``, ``tests/test_rolling_shutter.py``,
``tests/test_laser_colour.py``)."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any


def stage_outputs(res: Path, stage: str, **files: str) -> dict[str, str]:
    """A stage's outputs in ``res`` as the workflow names them: its rerun log, its report
    in ``reports/`` and ``files`` (output name -> file name)."""
    return {"rrd": str(res / f"{stage}.rrd"),
            "report": str(res / "reports" / f"{stage}.json"),
            **{k: str(res / v) for k, v in files.items()}}


def laser_point_distances_mm(rec: Path, out: Path, cfg: Mapping[str, Any],
                             min_points: int = 1, in_box: bool = False) -> Any:
    """The stripes and triangulation stages on ``rec`` (files in ``out``, created; the
    stripes report in ``out/reports/stripes.json``): each triangulated point's distance
    to the recording's true surface, mm ((N,) array); with ``in_box`` only the points in
    the workspace box (not the triangulation's margin around it)."""
    import numpy as np

    from robo3d.artefacts import in_clouds_workspace, load_clouds_npz
    from robo3d.evaluate import TruthSurface
    from robo3d.meshio import read_mesh
    from robo3d.pipeline import STAGES
    from robo3d.recording.reader import read_recording

    (out / "reports").mkdir(parents=True)
    s = stage_outputs(out, "stripes", npz="stripes.npz")
    c = stage_outputs(out, "triangulate", npz="clouds.npz", ply="clouds.ply")
    STAGES["stripes"]({"recording": str(rec)}, s, cfg, out.name, threads=1)
    STAGES["triangulate"]({"recording": str(rec), "stripes": s["npz"]}, c, cfg, out.name)
    r = read_recording(rec, roles=("laser",))
    truth = TruthSurface(*read_mesh(bytes(r.attachments["ground_truth/mesh.ply"]),
                                    suffix=".ply"))
    clouds = load_clouds_npz(c["npz"])
    keep = in_clouds_workspace(clouds) if in_box else [slice(None)] * len(clouds)
    pts = np.concatenate([cl.points_base[k] for cl, k in zip(clouds, keep, strict=True)])
    assert len(pts) >= min_points, (len(pts), min_points)
    return truth.distance(pts) * 1e3


def run_up_to_align(rec: Path, res: Path, cfg: Mapping[str, Any], name: str,
                    threads: int = 1) -> None:
    """silhouettes, carve, stripes, triangulate and align on ``rec``, their files in
    ``res`` (created, with ``reports/``)."""
    from robo3d.pipeline import (
        stage_align,
        stage_carve,
        stage_silhouettes,
        stage_stripes,
        stage_triangulate,
    )

    (res / "reports").mkdir(parents=True, exist_ok=True)
    r = str(rec)
    stage_silhouettes({"recording": r}, stage_outputs(res, "silhouettes", npz="silhouettes.npz"),
                      cfg, name)
    stage_carve({"silhouettes": str(res / "silhouettes.npz")},
                stage_outputs(res, "carve", npz="hull.npz", ply="hull.ply"), cfg, name)
    stage_stripes({"recording": r}, stage_outputs(res, "stripes", npz="stripes.npz"), cfg,
                  name, threads=threads)
    stage_triangulate({"stripes": str(res / "stripes.npz")},
                      stage_outputs(res, "triangulate", npz="clouds.npz", ply="clouds.ply"),
                      cfg, name)
    stage_align({"clouds": str(res / "clouds.npz"), "recording": r,
                 "silhouettes": str(res / "silhouettes.npz"), "hull": str(res / "hull.npz")},
                stage_outputs(res, "align", npz="aligned.npz", ply="aligned.ply"), cfg, name)
