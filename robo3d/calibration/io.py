"""A calibration's file (``results/calibration/<calib>.yaml``) and its use by a scan.

:class:`CalibrationFile` is what the ``calibrate`` rule writes
(:func:`write_calibration`, atomically: a failed or killed job leaves no file that looks
finished) and what a scan's stages read (:func:`read_calibration`, which checks every
key and says which one of which file is wrong). :func:`apply_calibration` makes a scan
recording use it: the camera model of its camera frame, its static ``flange -> camera``
(hand-eye) and ``camera -> laser`` links are replaced, not added beside the recorded ones.

The file, all lengths in metres, 4x4 matrices as nested lists (row-major)::

    name: kuka1                       # the calibration recording's name
    camera: {frame_id, width, height, K: [9], D: [5], distortion_model: plumb_bob}
    T_flange_camera: 4x4 | null       # null: a fixed-camera rig (moving target)
    T_camera_laser: 4x4 | null        # null: no laser frames in the calibration
    laser_sheet: {normal: [3], offset_m, six_parameters: {dx, dy, dz (m), phi_deg,
                  theta_deg, psi_deg}, rms_mm} | null
    quality: {rms_px, per_view_rms_px, handeye_rms_px, board_scatter_mm, sheet_rms_mm,
              views_used, views_left_out: {index: reason}, ...}
    gates: {name: {value, limit, passed}}
    source: {recording, kind, target, code}

Choices:

* The camera replaced is the recording's calibration whose ``frame_id`` is the file's; a
  recording with a single calibration under another name gets it under its own name (the
  same camera recorded with another ``frame_id``); an image size other than the file's
  is an error (a calibration is for one resolution).
* The hand-eye replaces the camera's own link. When the camera hangs from the flange
  through other fixed links (``flange -> mount -> camera``), the camera's link becomes
  ``T_mount_flange @ T_flange_camera`` so that the chain gives the calibrated pose; the
  laser likewise keeps its recorded parent. A link that would have to pass through a
  moving one is an error: the calibration cannot apply to that recording.
* A calibration without a hand-eye (fixed rig) leaves the recorded poses as they are.
"""

from __future__ import annotations

import copy
import os
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from ..atomic import atomic_path
from ..camera import CameraModel
from ..errors import CalibrationError
from ..transforms import TransformBuffer

__all__ = ["CalibrationFile", "write_calibration", "read_calibration", "apply_calibration",
           "calibration_note", "CALIBRATION_METADATA"]

#: The metadata record :func:`apply_calibration` adds to a recording it changed.
CALIBRATION_METADATA = "robo3d.calibration"

_REQUIRED = ("camera", "T_flange_camera", "T_camera_laser")
_SIX = ("dx_m", "dy_m", "dz_m", "phi_deg", "theta_deg", "psi_deg")


@dataclass
class CalibrationFile:
    """One calibration: intrinsics, hand-eye, laser sheet, how good they are, where from.

    Attributes
    ----------
    name : str
        The calibration recording's name (``results/calibration/<name>.yaml``).
    camera : CameraModel
        Intrinsics (K in pixels, plumb_bob D) at the calibration's image size.
    T_flange_camera : (4, 4) float64 or None
        Hand-eye, metres; None for a fixed-camera rig.
    T_camera_laser : (4, 4) float64 or None
        The laser's pose in the camera (its sheet is the laser frame's x-z plane).
    laser_sheet : dict or None
        The sheet as a plane (``normal``, ``offset_m``), the seed's six parameters
        (eq. 11) and the fit's residual ``rms_mm``.
    quality, gates, source : dict
        The figures of the fit, the quality gates' table, the recording and code.
    path : str or None
        The file it was read from (None until written or read).
    """

    name: str
    camera: CameraModel
    T_flange_camera: np.ndarray | None = None
    T_camera_laser: np.ndarray | None = None
    laser_sheet: dict[str, Any] | None = None
    distortion_model: str = "plumb_bob"
    quality: dict[str, Any] = field(default_factory=dict)
    gates: dict[str, Any] = field(default_factory=dict)
    source: dict[str, Any] = field(default_factory=dict)
    path: str | None = None

    def as_dict(self) -> dict[str, Any]:
        """The YAML document (plain lists and numbers)."""
        cam = self.camera
        return _plain({
            "name": self.name,
            "camera": {"frame_id": cam.frame_id, "width": int(cam.width),
                       "height": int(cam.height), "K": cam.K.reshape(-1),
                       "D": cam.D.reshape(-1), "distortion_model": self.distortion_model},
            "T_flange_camera": self.T_flange_camera,
            "T_camera_laser": self.T_camera_laser,
            "laser_sheet": self.laser_sheet,
            "quality": self.quality,
            "gates": self.gates,
            "source": self.source,
        })


def _plain(x: Any) -> Any:
    """Numpy arrays and scalars as lists and Python numbers (safe YAML)."""
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, Mapping):
        return {str(k) if not isinstance(k, int) else k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, os.PathLike):
        return os.fspath(x)
    return x


def write_calibration(path: str | os.PathLike[str], calib: CalibrationFile) -> None:
    """Write ``calib`` as YAML to ``path``, atomically (a temporary file renamed when
    complete). The document is read back and checked first: a file this function writes
    is one :func:`read_calibration` accepts."""
    import yaml

    doc = calib.as_dict()
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    _parse(yaml.safe_load(text), str(path))  # never write what cannot be read
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        f.write("# robo3d calibration (metres, pixels; T_a_b maps b to a). "
                "Written by the calibrate rule.\n")
        f.write(text)


def read_calibration(path: str | os.PathLike[str]) -> CalibrationFile:
    """Read and check a calibration file.

    Raises
    ------
    CalibrationError
        Naming the file and the key: unreadable YAML, a missing key, a matrix of the
        wrong shape, non-finite numbers, a rotation that is not one.
    """
    import yaml

    spath = os.fspath(path)
    try:
        with open(spath, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise CalibrationError(f"cannot read the calibration file: {exc}", path=spath) from None
    except yaml.YAMLError as exc:
        raise CalibrationError(f"not valid YAML: {exc}", path=spath) from None
    return _parse(doc, spath)


def _fail(path: str, key: str, what: str) -> CalibrationError:
    return CalibrationError(f"calibration key {key}: {what}", path=path)


def _numbers(value: Any, path: str, key: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, key, f"must be numbers of shape {shape}, got {value!r}") from None
    if a.size == int(np.prod(shape)):
        a = a.reshape(shape)
    if a.shape != shape:
        raise _fail(path, key, f"must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise _fail(path, key, "holds non-finite numbers")
    return a


def _transform(value: Any, path: str, key: str) -> np.ndarray | None:
    if value is None:
        return None
    T = _numbers(value, path, key, (4, 4))
    R = T[:3, :3]
    if (np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or abs(np.linalg.det(R) - 1) > 1e-6
            or np.abs(T[3] - [0, 0, 0, 1]).max() > 1e-12):
        raise _fail(path, key, "is not a rigid transform (its rotation is not orthonormal "
                    "with determinant 1, or its last row is not 0 0 0 1)")
    return T


def _parse(doc: Any, path: str) -> CalibrationFile:
    if not isinstance(doc, dict):
        raise CalibrationError(f"a calibration file must be a mapping, got "
                               f"{type(doc).__name__}", path=path)
    missing = [k for k in _REQUIRED if k not in doc]
    if missing:
        raise _fail(path, missing[0], f"missing (a calibration file has {', '.join(_REQUIRED)}"
                    f", laser_sheet, quality, gates, source)")
    cam = doc["camera"]
    if not isinstance(cam, dict):
        raise _fail(path, "camera", f"must be a mapping, got {cam!r}")
    for k in ("frame_id", "width", "height", "K", "D"):
        if k not in cam:
            raise _fail(path, f"camera.{k}", "missing")
    size = []
    for k in ("width", "height"):
        if not isinstance(cam[k], int) or isinstance(cam[k], bool) or cam[k] <= 0:
            raise _fail(path, f"camera.{k}", f"must be a positive integer, got {cam[k]!r}")
        size.append(cam[k])
    K = _numbers(cam["K"], path, "camera.K", (3, 3))
    D = np.asarray(cam["D"] if cam["D"] is not None else [], dtype=object).reshape(-1)
    if D.size not in (0, 4, 5, 8):
        raise _fail(path, "camera.D", f"plumb_bob needs 5 coefficients, got {D.size}")
    D = _numbers(list(D), path, "camera.D", (D.size,)) if D.size else np.zeros(5)
    model = cam.get("distortion_model", "plumb_bob")
    if model not in ("plumb_bob", "rational_polynomial", "", None):
        raise _fail(path, "camera.distortion_model", f"must be plumb_bob, got {model!r}")
    try:
        camera = CameraModel(str(cam["frame_id"]), size[0], size[1], K, D)
    except CalibrationError as exc:
        raise _fail(path, "camera", exc.reason) from None
    sheet = doc.get("laser_sheet")
    if sheet is not None:
        if not isinstance(sheet, dict):
            raise _fail(path, "laser_sheet", f"must be a mapping or null, got {sheet!r}")
        if "normal" in sheet:
            n = _numbers(sheet["normal"], path, "laser_sheet.normal", (3,))
            if abs(np.linalg.norm(n) - 1) > 1e-6:
                raise _fail(path, "laser_sheet.normal", f"must be a unit vector, got "
                            f"length {np.linalg.norm(n):.6g}")
        for k in ("offset_m", "rms_mm"):
            if k in sheet and sheet[k] is not None:
                _numbers(sheet[k], path, f"laser_sheet.{k}", ())
    for k in ("quality", "gates", "source"):
        if doc.get(k) is not None and not isinstance(doc[k], dict):
            raise _fail(path, k, f"must be a mapping, got {type(doc[k]).__name__}")
    name = doc.get("name") or Path(path).stem
    return CalibrationFile(
        name=str(name), camera=camera,
        T_flange_camera=_transform(doc["T_flange_camera"], path, "T_flange_camera"),
        T_camera_laser=_transform(doc["T_camera_laser"], path, "T_camera_laser"),
        laser_sheet=copy.deepcopy(sheet), distortion_model=str(model or "plumb_bob"),
        quality=dict(doc.get("quality") or {}), gates=dict(doc.get("gates") or {}),
        source=dict(doc.get("source") or {}), path=path)


# ---------------------------------------------------------------------------- applying
def _parents(buf: TransformBuffer) -> dict[str, tuple[str, bool]]:
    return {child: (parent, static) for parent, child, static, _ in buf.links()}


def _static_between(buf: TransformBuffer, a: str, b: str) -> bool:
    """Whether every link on the chain between frames ``a`` and ``b`` is static."""
    par = _parents(buf)

    def up(f: str) -> list[str]:
        out = [f]
        while out[-1] in par and len(out) <= len(par):
            out.append(par[out[-1]][0])
        return out

    ua, ub = up(a), up(b)
    common = next((f for f in ua if f in set(ub)), None)
    if common is None:
        return False
    return all(par[f][1] for f in ua[: ua.index(common)] + ub[: ub.index(common)])


def _camera_key(rec, calib: CalibrationFile) -> str:
    fid = calib.camera.frame_id
    if fid in rec.calibrations:
        return fid
    if "camera" in rec.calibrations:
        return "camera"
    if len(rec.calibrations) == 1:
        return next(iter(rec.calibrations))
    if not rec.calibrations:
        return fid
    raise CalibrationError(f"calibration {calib.path or calib.name}: camera {fid!r} is not "
                           f"among the recording's cameras ({', '.join(sorted(rec.calibrations))})"
                           "; which one it calibrates is ambiguous", path=rec.path)


def _relink(buf: TransformBuffer, parent_role: str, frame: str, T_role_frame: np.ndarray,
            what: str, where: str, rec_path: str) -> None:
    """Make the chain give ``T_role_frame`` by replacing ``frame``'s own static link."""
    par = _parents(buf)
    if frame not in par:
        raise CalibrationError(f"{where}: the recording has no link to frame {frame!r}, so "
                               f"its {what} cannot be replaced", path=rec_path)
    parent = par[frame][0]
    if parent == parent_role:
        buf.replace_static(parent, frame, T_role_frame)
        return
    if parent_role not in buf.frames or not _static_between(buf, parent, parent_role):
        raise CalibrationError(
            f"{where}: the recording's {frame!r} hangs from {parent!r}, which is not fixed to "
            f"{parent_role!r} (no {parent_role!r} frame, or a moving link between them): the "
            f"calibrated {what} does not apply to this recording", path=rec_path)
    T_parent_role = buf.lookup(parent, parent_role, 0)
    buf.replace_static(parent, frame, T_parent_role @ T_role_frame)


def apply_calibration(recording, calib: CalibrationFile | str | os.PathLike[str]):
    """A copy of ``recording`` that uses ``calib``'s camera model, hand-eye and laser.

    Parameters
    ----------
    recording : robo3d.recording.Recording
        As the reader returned it (frame names are roles: ``flange``, ``laser``).
    calib : CalibrationFile or path
        The calibration (a path is read with :func:`read_calibration`).

    Returns
    -------
    Recording
        A new recording (the input is not changed) whose ``calibrations`` entry for the
        camera is the calibrated model (which describes the raw images, as the calibrate
        stage estimates it from them: a ``rational_polynomial`` camera's images are then
        no longer rectified), whose static ``flange -> camera`` and ``camera ->
        laser`` links are the calibrated ones (replaced, not added), and whose metadata
        record ``robo3d.calibration`` says which file they came from (:func:`calibration_note`).

    Raises
    ------
    CalibrationError
        The recording's images have another size than the calibration's, its camera is
        ambiguous, or its transform tree cannot take the calibrated links.
    """
    if not isinstance(calib, CalibrationFile):
        calib = read_calibration(calib)
    where = f"calibration {calib.path or calib.name}"
    key = _camera_key(recording, calib)
    old = recording.calibrations.get(key)
    if old is not None and (old.width, old.height) != (calib.camera.width, calib.camera.height):
        raise CalibrationError(
            f"{where} is for {calib.camera.width}x{calib.camera.height} images, the recording's "
            f"camera {key!r} records {old.width}x{old.height}: a calibration holds for one "
            "resolution", path=recording.path)
    cams = dict(recording.calibrations)
    cams[key] = CameraModel(key, calib.camera.width, calib.camera.height, calib.camera.K,
                            calib.camera.D)
    buf = recording.tf.copy()
    replaced = []
    if calib.T_flange_camera is not None:
        _relink(buf, "flange", key, calib.T_flange_camera, "hand-eye (flange -> camera)",
                where, recording.path)
        replaced.append("flange->camera")
    if calib.T_camera_laser is not None and "laser" in buf.frames:
        _relink(buf, key, "laser", calib.T_camera_laser, "laser (camera -> laser)", where,
                recording.path)
        replaced.append("camera->laser")
    metadata = dict(recording.metadata)
    metadata[CALIBRATION_METADATA] = {**calibration_note(calib), "camera": key,
                                      "replaced": " ".join(["intrinsics"] + replaced)}
    rectifiers = {fid: r for fid, r in recording.rectifiers.items() if fid != key}
    return replace(recording, calibrations=cams, tf=buf, metadata=metadata,
                   rectifiers=rectifiers)


def calibration_note(calib: CalibrationFile | str | os.PathLike[str]) -> dict[str, str]:
    """What a scan's metrics say about the calibration it used: the file, the calibration
    recording it came from and its headline figures (strings, as metadata values are)."""
    if not isinstance(calib, CalibrationFile):
        calib = read_calibration(calib)
    q = calib.quality
    note = {"file": str(calib.path or ""), "name": calib.name,
            "recording": str(calib.source.get("recording", ""))}
    for k in ("rms_px", "handeye_rms_px", "board_scatter_mm", "sheet_rms_mm"):
        if q.get(k) is not None:
            note[k] = f"{float(q[k]):.6g}"
    return note
