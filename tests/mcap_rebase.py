"""A recording re-expressed in a turned ``base`` frame: the same scan as a robot mounted
upside down (on a ceiling) or a converter whose base has y up would record it. Every
transform out of ``base`` on ``/tf`` and ``/tf_static`` (protobuf or JSON
``foxglove.FrameTransforms``), the workspace box (the axis-aligned box around the
turned one) and the ground truth (``mesh.ply``, ``tf.json``, ``image_poses.json``) are
turned by ``R``; images and everything else are copied as they are. The simulation's
metadata record is left out: it describes the scene in the simulator's z-up base."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np


def _turn(R: np.ndarray, t: dict, q: dict) -> tuple[np.ndarray, np.ndarray]:
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat([q["x"], q["y"], q["z"], q["w"]]).as_matrix()
    T[:3, 3] = [t["x"], t["y"], t["z"]]
    T[:3] = R @ T[:3]
    return T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_quat()


def _turn_json(R: np.ndarray, msg: dict) -> dict:
    for tr in msg.get("transforms", [msg] if "parent_frame_id" in msg else []):
        if tr.get("parent_frame_id") == "base":
            p, q = _turn(R, tr.get("translation", {"x": 0, "y": 0, "z": 0}),
                         tr.get("rotation", {"x": 0, "y": 0, "z": 0, "w": 1}))
            tr["translation"] = dict(zip("xyz", map(float, p), strict=True))
            tr["rotation"] = dict(zip("xyzw", map(float, q), strict=True))
    return msg


def _turn_pb(R: np.ndarray, data: bytes, schema: str) -> bytes:
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.FrameTransforms_pb2 import FrameTransforms

    msg = FrameTransforms() if schema == "foxglove.FrameTransforms" else FrameTransform()
    msg.ParseFromString(data)
    for tr in (msg.transforms if schema == "foxglove.FrameTransforms" else [msg]):
        if tr.parent_frame_id == "base":
            t, r = tr.translation, tr.rotation
            p, q = _turn(R, {"x": t.x, "y": t.y, "z": t.z},
                         {"x": r.x, "y": r.y, "z": r.z, "w": r.w})
            t.x, t.y, t.z = map(float, p)
            r.x, r.y, r.z, r.w = map(float, q)
    return msg.SerializeToString()


def _turn_mesh(R: np.ndarray, data: bytes) -> bytes:
    import tempfile

    import open3d as o3d

    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "m.ply"
        p.write_bytes(data)
        m = o3d.io.read_triangle_mesh(str(p))
        m.vertices = o3d.utility.Vector3dVector(np.asarray(m.vertices) @ R.T)
        o3d.io.write_triangle_mesh(str(p), m)
        return p.read_bytes()


def _turn_metadata(R: np.ndarray, name: str, meta: dict[str, str]) -> dict[str, str] | None:
    if name == "robo3d.simulation":
        return None
    if "workspace_min" in meta:
        from robo3d.carving import turn_box

        lo, hi = turn_box(R, [np.array(meta[k].split(), float)
                              for k in ("workspace_min", "workspace_max")])
        meta["workspace_min"] = " ".join(f"{x:.6f}" for x in lo)
        meta["workspace_max"] = " ".join(f"{x:.6f}" for x in hi)
    return meta


def _turn_attachment(R: np.ndarray, name: str, data: bytes) -> bytes:
    if name == "ground_truth/mesh.ply":
        return _turn_mesh(R, data)
    if name == "ground_truth/tf.json":
        return json.dumps(_turn_json(R, json.loads(data))).encode()
    if name == "ground_truth/image_poses.json":
        poses = json.loads(data)
        for rows in poses.values():
            for row in rows if isinstance(rows, list) else ():
                T = np.array(row["T_base_camera"], float).reshape(4, 4)
                T[:3] = R @ T[:3]
                row["T_base_camera"] = T.reshape(-1).tolist()
        return json.dumps(poses).encode()
    return data


def _turn_message(R: np.ndarray, schema: str, encoding: str, data: bytes) -> bytes:
    if schema not in ("foxglove.FrameTransforms", "foxglove.FrameTransform"):
        return data
    if encoding == "protobuf":
        return _turn_pb(R, data, schema)
    return json.dumps(_turn_json(R, json.loads(data))).encode()


def rebase_recording(src: Path, dst: Path, R: np.ndarray) -> Path:
    """Copy ``src`` to ``dst`` with ``base`` turned by the rotation ``R`` (a point ``x``
    in the old base is ``R @ x`` in the new)."""
    from mcap_copy import copy_recording

    R = np.asarray(R, dtype=np.float64)
    return copy_recording(src, dst, metadata=lambda n, m: _turn_metadata(R, n, dict(m)),
                          message=lambda s, e, d: _turn_message(R, s, e, d),
                          attachment=lambda n, d: _turn_attachment(R, n, d))
