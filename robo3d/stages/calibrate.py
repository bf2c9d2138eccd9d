"""The ``calibrate`` stage: a ``kind=calibration`` recording -> ``results/calibration/<calib>.yaml``
and its report (:mod:`robo3d.calibration.calibrate`).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from ..atomic import write_json
from .common import code_version, log, open_recording, summary


def _failed_report_path(report: str) -> Path:
    p = Path(report)
    return p.with_name(p.stem + ".failed" + p.suffix)


def stage_calibrate(inputs: Mapping[str, str], outputs: Mapping[str, str],
                    cfg: Mapping[str, Any], rec_name: str) -> dict[str, Any]:
    """Calibrate the camera (and hand-eye, laser sheet) from a calibration recording.

    Outputs: ``yaml`` (:func:`robo3d.calibration.io.write_calibration`), ``report``
    (:func:`robo3d.calibration.calibrate.calibration_report`: every view with its RMS or
    why it was left out, the gate table) and, when given, ``picture`` (a PNG of the views
    with their detected corners and of laser frames with the stripe the sheet used).
    A failed quality gate raises :class:`~robo3d.errors.CalibrationError` naming the
    gate and the likely cause; no calibration file is written then, and the report of the
    failed calibration goes to ``<report>.failed.json`` beside the report, to look at.
    """
    from ..calibration.calibrate import (
        GateFailure,
        calibrate_recording,
        calibration_report,
        to_calibration_file,
    )
    from ..calibration.io import write_calibration

    rec = open_recording(inputs["recording"], cfg, roles=("views", "laser"), require=False)
    failed_path = _failed_report_path(outputs["report"])
    try:
        result = calibrate_recording(rec, cfg, name=rec_name)
    except GateFailure as exc:
        write_json(failed_path, calibration_report(exc.result))
        log.error("the failed calibration's report: %s", failed_path)
        raise
    failed_path.unlink(missing_ok=True)
    report = calibration_report(result)
    if outputs.get("picture"):
        from ..calibration.calibrate import detection_picture

        detection_picture(outputs["picture"], rec, result)
    write_calibration(outputs["yaml"], to_calibration_file(result, code_version()))
    write_json(outputs["report"], report)
    he = (f", hand-eye {result.handeye_rms_px:.3f} px, board scatter "
          f"{result.board_scatter_mm:.2f} mm" if result.T_flange_camera is not None else "")
    sheet = (f", laser sheet {result.sheet_rms_mm:.3f} mm RMS" if result.sheet_rms_mm is not None
             else "")
    summary.info("calibrated from %d of %d views: %.3f px RMS%s%s; every gate passed (%.1f s)",
                 len(result.views_used), len(result.view_stamps_ns), result.rms_px, he, sheet,
                 result.seconds)
    return report
