"""End-to-end: a scan whose silhouettes fail keeps what its laser measured (the Snakemake
workflow on one small simulated cell recording). Its own file, apart from
``test_workflow.py``'s batch, so that the suite's two workers run them side by side."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_workflow import _metrics, _snakemake  # noqa: E402

from robo3d.simulate import simulate_recording  # noqa: E402

pytestmark = pytest.mark.slow


def test_a_scan_whose_silhouettes_fail_keeps_what_its_laser_measured(tmp_path):
    """A black bracket on a black-and-white marker table, which the colour model cannot
    separate: three of ten views give no silhouette at all and the rest specks. Before,
    the first empty view stopped the recording; and masks that all missed the object
    dropped every laser point. Now the failed views are named and left out, the
    silhouettes that contradict the laser drop nothing, they carve no hull, and the mesh
    is the measured surface, labelled so."""
    from robo3d.simulate import SimulationParams

    recs = tmp_path / "recs"
    recs.mkdir()
    params = SimulationParams.cell(laser="blue", object_color="black", wall=False, small=True,
                                   seed=12)
    simulate_recording(recs / "black_bracket.mcap", "bracket", params=params)
    _snakemake(tmp_path, "--config", f"recordings={recs}")
    m = _metrics(tmp_path, "black_bracket")
    assert m["stages"]["silhouettes"]["views_failed"]  # named, not fatal
    assert m["evaluation"]["mask_iou"]["mean"] < 0.5  # the masks are wrong ...
    hull_test = m["stages"]["align"]["outside_hull"]
    assert hull_test["contradicted"] is True and hull_test["dropped"] == 0  # ... the laser kept
    # every mask empty or disagreeing: no hull, and the carve says why ...
    assert m["stages"]["carve"]["empty"] is True
    assert "no view is left to carve" in m["stages"]["carve"]["reason"]
    assert m["surface_sources"]["inferred_area_fraction"] == 0.0
    # ... and fusion closes nothing, from the laser alone (its report said "holes closed
    # from the hull" before stop 45, then, until stop 61, that the empty hull contradicted
    # the laser: every measured point lay outside it)
    assert not m["surface_sources"]["hull_contradicted"]
    assert m["stages"]["fuse"]["source"] == "laser (TSDF)"
    ev = m["evaluation"]["measured"]
    # measured 5.5e-4 m2 (5.5 cm2) of the bracket's surface, median 0.18 mm, 22 % of it
    # more than 0.5 mm off (the robot's poses hold the gauge). Before fusion.max_frame_span
    # (stop 45) 1.2e-3 m2 at 0.27 mm, 43 % more than 0.5 mm off: the range surface bridged
    # frames whose blue stripe the black bracket did not return; before the table rule
    # (stop 35) 3.5e-3 m2 at 0.74 mm, the line on the table counted as measured
    assert ev["area_m2"] > 4e-4
    assert ev["median_mm"] < 0.3
    assert ev["outlier_area_fraction_0_5mm"] < 0.3
