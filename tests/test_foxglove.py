"""results.mcap for Foxglove (robo3d.foxglove, the foxglove stage), checked by a reader
that shares no code with the writer: rerun's MCAP importer (tests/foxglove_reader.py)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from foxglove_reader import read_results
from foxglove_schemas_protobuf.Color_pb2 import Color
from foxglove_schemas_protobuf.Point3_pb2 import Point3
from foxglove_schemas_protobuf.TriangleListPrimitive_pb2 import TriangleListPrimitive

from robo3d.artefacts import Silhouettes, Stripes, SweepCloud, load_clouds_npz, save_clouds_npz
from robo3d.camera import CameraModel
from robo3d.config import default_config
from robo3d.foxglove import (
    FoxgloveOptions,
    ResultMessage,
    point_cloud,
    scene_update,
    thin,
    write_results_mcap,
)
from robo3d.meshio import read_mesh, write_mesh
from robo3d.stages.common import sweep_color
from robo3d.stages.foxglove import stage_foxglove
from robo3d.stages.fuse import source_colors

T0 = 1_700_000_000_000_000_000  # the synthetic recording's clock, ns


def _octahedron(radius: float, levels: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A sphere-like closed mesh: an octahedron split ``levels`` times, on the sphere."""
    V = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    F = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5],
                  [3, 1, 5], [0, 3, 5]])
    for _ in range(levels):
        edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        uniq, inv = np.unique(edges, axis=0, return_inverse=True)
        mid = len(V) + inv.reshape(3, -1).T  # (F, 3): midpoints of edges 01, 12, 20
        V = np.concatenate([V, V[uniq].mean(axis=1)])
        a, b, c = F.T
        ab, bc, ca = mid.T
        F = np.concatenate([np.stack(t, 1) for t in
                            ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return radius * V / np.linalg.norm(V, axis=1, keepdims=True), F


@pytest.fixture(scope="module")
def scan(tmp_path_factory) -> dict:
    """Synthetic results of a recording: 2 sweeps of 8 laser frames (a gap between
    them), 4 views, points on a 30 mm sphere, the mesh with every provenance, the hull."""
    d = tmp_path_factory.mktemp("fox")
    rng = np.random.default_rng(1)
    laser = T0 + np.concatenate([np.arange(8), 30 + np.arange(8)]) * 100_000_000
    views = T0 + np.arange(4) * 500_000_000 + 100  # before the laser frames
    cam = CameraModel("camera", 64, 48, np.array([[50, 0, 32], [0, 50, 24], [0, 0, 1.0]]))
    eye = np.broadcast_to(np.eye(4), (16, 4, 4)).copy()
    Stripes(u=np.zeros(0), v=np.zeros(0), confidence=np.zeros(0),
            offsets=np.zeros(17, np.int64), stamps_ns=laser, T_base_camera=eye,
            cameras=[cam] * 16).save(d / "stripes.npz")
    Silhouettes.from_views([np.zeros((48, 64), bool)] * 4, eye[:4], views, [cam] * 4,
                           [False] * 4).save(d / "silhouettes.npz")
    clouds = []
    for k in range(2):  # frame 3 of sweep 0 saw nothing
        frames = np.repeat([f for f in range(8 * k, 8 * k + 8) if f != 3], 40 + 10 * k)
        p = rng.normal(size=(len(frames), 3))
        p = 0.03 * p / np.linalg.norm(p, axis=1, keepdims=True)
        clouds.append(SweepCloud(p, -p / 0.03, frames, rng.uniform(size=len(frames)), k,
                                 np.zeros((len(frames), 3))))
    save_clouds_npz(d / "clouds.npz", clouds)
    save_clouds_npz(d / "aligned.npz", [SweepCloud(c.points_base + 1e-4, c.normals_base,
                                                   c.frame_index, c.confidence, c.sweep,
                                                   c.sensor_origin_base) for c in clouds])
    V, F = _octahedron(0.03)
    source = (np.arange(len(V)) % 3).astype(np.uint8)  # measured, hull, filled
    write_mesh(d / "mesh.ply", V, F, vertex_colors=source_colors(source),
               attributes={"source": source})
    Vh, Fh = _octahedron(0.032, levels=2)
    write_mesh(d / "hull.ply", Vh, Fh)
    inputs = {k: str(d / f"{k}.npz") for k in ("stripes", "silhouettes", "clouds", "aligned")}
    inputs.update(mesh=str(d / "mesh.ply"), hull=str(d / "hull.ply"))
    return {"dir": d, "inputs": inputs, "laser": laser, "views": views}


def _run(scan: dict, name: str, **foxglove) -> tuple[dict, Path]:
    cfg = default_config()
    cfg["foxglove"].update(foxglove)
    out = scan["dir"] / name
    report = stage_foxglove(scan["inputs"], {"mcap": str(out)}, cfg, "synthetic")
    return report, out


# ---------------------------------------------------------------------------- feature
def test_results_read_by_an_independent_reader(scan):
    """What a Foxglove user gets, as rerun's MCAP importer reads it: the schemas, frame
    base, every point of each sweep at its last frame's time with the sweep's colour and
    the layout x y z float32 + RGBA, each frame's profile at its time, the meshes with
    mesh.ply's triangles at the end, all within the recording's time range."""
    report, path = _run(scan, "results.mcap")
    res = read_results(path)
    laser, views = scan["laser"], scan["views"]
    start, end = int(min(laser.min(), views.min())), int(max(laser.max(), views.max()))
    # schemas, encodings, the recording's clock
    assert set(res.encodings.values()) == {"protobuf"}
    clouds = {t for t, s in res.schemas.items() if s == "foxglove.PointCloud"}
    assert clouds == {"/results/raw/sweep_00", "/results/raw/sweep_01",
                      "/results/aligned/sweep_00", "/results/aligned/sweep_01",
                      "/results/aligned/profile"}
    assert res.schemas["/results/mesh"] == res.schemas["/results/hull"] == "foxglove.SceneUpdate"
    assert start <= res.start_ns and res.end_ns <= end
    assert res.metadata["robo3d.results"]["frame_id"] == "base"
    # every cloud: frame base, stamp = log time, the layout
    assert all(c.frame_id == "base" and c.stamp_ns == c.log_time_ns for c in res.clouds)
    layout = [("x", 0, "FLOAT32"), ("y", 4, "FLOAT32"), ("z", 8, "FLOAT32"),
              ("red", 12, "UINT8"), ("green", 13, "UINT8"), ("blue", 14, "UINT8"),
              ("alpha", 15, "UINT8"), ("confidence", 16, "FLOAT32"), ("sweep", 20, "UINT32")]
    assert all(c.fields == layout and c.point_stride == 24 for c in res.clouds)
    for key, topic in (("clouds", "/results/raw"), ("aligned", "/results/aligned")):
        npz = load_clouds_npz(scan["inputs"][key])
        msgs = {c.topic: c for c in res.clouds if c.topic.startswith(topic + "/sweep")}
        assert sum(len(m.positions) for m in msgs.values()) == sum(len(c) for c in npz)
        assert report["points"][key] == sum(len(c) for c in npz)
        for c in npz:
            m = msgs[f"{topic}/sweep_{c.sweep:02d}"]
            np.testing.assert_allclose(m.positions, c.points_base, atol=1e-8)
            assert m.stamp_ns == laser[c.frame_index.max()]  # the sweep's last frame
            r, g, b = sweep_color(c.sweep)
            assert set(m.colors_rgba.tolist()) == {(r << 24) | (g << 16) | (b << 8) | 255}
    # the profiles: one per laser frame that has points, at that frame's time
    aligned = load_clouds_npz(scan["inputs"]["aligned"])
    frames = np.concatenate([c.frame_index for c in aligned])
    prof = [c for c in res.clouds if c.topic == "/results/aligned/profile"]
    assert [p.stamp_ns for p in prof] == laser[np.unique(frames)].tolist()
    assert [len(p.positions) for p in prof] == np.bincount(frames)[np.unique(frames)].tolist()
    # the meshes: mesh.ply's triangles, coloured per vertex; the hull translucent
    meshes = {m.entity_id: m for m in res.meshes}
    V, F = read_mesh(scan["inputs"]["mesh"])
    Vh, Fh = read_mesh(scan["inputs"]["hull"])
    assert (meshes["mesh"].n_triangles, meshes["mesh"].n_vertices) == (len(F), len(V))
    assert meshes["mesh"].n_vertex_colors == len(V)
    assert meshes["hull"].n_triangles == len(Fh) and meshes["hull"].color["a"] < 1
    for m in meshes.values():
        assert m.frame_id == "base" and m.stamp_ns == m.log_time_ns == end


def test_results_are_deterministic(scan):
    """The same inputs give the same bytes (no wall-clock time in the file)."""
    _, a = _run(scan, "a.mcap")
    _, b = _run(scan, "b.mcap")
    assert a.read_bytes() == b.read_bytes()


def test_a_renamed_base_frame_is_joined_to_base(scan):
    """frames.base: base_link (a ROS cell) -> an identity base_link -> base link, so that
    the results in base meet the recording's transform tree."""
    cfg = default_config()
    cfg["frames"]["base"] = "base_link"
    out = scan["dir"] / "ros.mcap"
    stage_foxglove(scan["inputs"], {"mcap": str(out)}, cfg, "synthetic")
    res = read_results(out)
    assert res.schemas["/results/tf_static"] == "foxglove.FrameTransforms"
    assert res.counts["/results/tf_static"] == 1
    assert res.metadata["robo3d.results"]["recording_base_frame"] == "base_link"


def test_max_points_and_profiles_options(scan):
    report, path = _run(scan, "thin.mcap", max_points=25, profiles=False)
    res = read_results(path)
    assert "/results/aligned/profile" not in res.schemas
    assert all(len(c.positions) == 25 for c in res.clouds)
    assert set(report["messages"]) == set(res.counts)


def test_meshes_option_and_a_laser_only_recording(scan):
    """Without views there are no view stamps and no hull; fused and measured on request."""
    d = scan["dir"]
    write_mesh(d / "measured.ply", *_octahedron(0.03, levels=1))
    inputs = {k: v for k, v in scan["inputs"].items() if k not in ("silhouettes", "hull")}
    inputs["measured"] = str(d / "measured.ply")
    cfg = default_config()
    stage_foxglove(inputs, {"mcap": str(d / "laser.mcap")}, cfg, "synthetic")
    res = read_results(d / "laser.mcap")
    assert {m.entity_id for m in res.meshes} == {"mesh", "measured"}
    assert res.end_ns == scan["laser"].max()


# ---------------------------------------------------------------------------- shape
def test_scene_update_wire_bytes_equal_the_protobuf_api():
    """The numpy-built repeated Point3 / Color / indices parse to the same message as
    one built element by element with the Protobuf API."""
    V, F = _octahedron(0.01, levels=1)
    rgba = np.random.default_rng(0).integers(0, 256, size=(len(V), 4)).astype(np.uint8)
    tri = scene_update("m", V, F, T0, colors=rgba).entities[0].triangles[0]
    ref = TriangleListPrimitive(
        points=[Point3(x=x, y=y, z=z) for x, y, z in V],
        colors=[Color(r=r / 255, g=g / 255, b=b / 255, a=a / 255) for r, g, b, a in rgba],
        indices=F.reshape(-1).tolist())
    ref.pose.orientation.w = 1.0
    ref.pose.position.x = 0.0
    assert tri == ref


def test_point_cloud_record_layout():
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    msg = point_cloud(pts, np.array([[1, 2, 3], [4, 5, 6]], np.uint8), T0 + 5,
                      fields={"confidence": np.array([0.5, 1.0], np.float32)})
    rec = np.frombuffer(msg.data, dtype=np.dtype(
        [("xyz", "<f4", 3), ("rgba", "u1", 4), ("confidence", "<f4")]))
    assert msg.point_stride == 20 and msg.frame_id == "base"
    assert (msg.timestamp.seconds, msg.timestamp.nanos) == (T0 // 10**9, 5)
    np.testing.assert_array_equal(rec["xyz"], pts)
    np.testing.assert_array_equal(rec["rgba"], [[1, 2, 3, 255], [4, 5, 6, 255]])
    assert point_cloud(np.zeros((0, 3)), (1, 2, 3), 0).data == b""


def test_thin_keeps_ends_and_count():
    assert thin(10, 0).tolist() == list(range(10))
    assert thin(5, 10).tolist() == list(range(5))
    k = thin(1000, 7)
    assert len(k) == 7 and k[0] == 0 and k[-1] == 999


def test_options_from_config():
    assert FoxgloveOptions.from_config(default_config()["foxglove"]) == FoxgloveOptions()


# ---------------------------------------------------------------------------- exception
def test_bad_inputs_are_named():
    with pytest.raises(ValueError, match="points_base"):
        point_cloud(np.zeros((3, 2)), (1, 2, 3), 0)
    with pytest.raises(ValueError, match="colors"):
        point_cloud(np.zeros((3, 3)), (1, 2, 300), 0)
    with pytest.raises(ValueError, match="'red'"):
        point_cloud(np.zeros((3, 3)), (1, 2, 3), 0, fields={"red": np.zeros(3, np.uint8)})
    with pytest.raises(ValueError, match="faces"):
        scene_update("m", np.zeros((3, 3)), np.array([[0, 1, 3]]), 0)


def test_a_failed_write_leaves_no_file(tmp_path):
    """A message that cannot be written aborts the file: nothing under its name, no
    temporary left beside it."""
    good = ResultMessage("/a", T0, point_cloud(np.zeros((2, 3)), (1, 2, 3), T0))
    with pytest.raises(ValueError, match="protobuf message"):
        write_results_mcap(tmp_path / "results.mcap",
                           [good, ResultMessage("/b", T0 + 1, object())])
    assert list(tmp_path.iterdir()) == []


def test_a_json_recording_writer_refuses_protobuf_results(tmp_path):
    from robo3d.recording.writer import RecordingWriter

    with RecordingWriter(tmp_path / "r.mcap", message_encoding="json") as w, \
            pytest.raises(ValueError, match="message_encoding='protobuf'"):
        w.write_protobuf("/a", 0, point_cloud(np.zeros((1, 3)), (1, 2, 3), 0))
