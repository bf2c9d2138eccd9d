"""meshio: PLY/STL/OBJ round trips, point clouds with attributes, atomic writes, errors."""

from __future__ import annotations

import numpy as np
import pytest

from robo3d import meshio
from robo3d.errors import StageError


def _mesh():
    import open3d as o3d

    m = o3d.geometry.TriangleMesh.create_icosahedron(0.05).subdivide_midpoint(1)
    v = np.asarray(m.vertices) + [0.512345678901, -0.1, 0.3]
    return v, np.asarray(m.triangles).astype(np.int64)


def _tri_set(v, f, decimals=6):
    """Triangles as sorted tuples of rounded coordinates (order independent)."""
    t = np.round(v[f] * 1e3, decimals)
    return {tuple(sorted(map(tuple, tri))) for tri in t}


@pytest.mark.parametrize("suffix", [".ply", ".obj"])
def test_mesh_round_trip_exact(tmp_path, suffix):
    v, f = _mesh()
    path = tmp_path / f"m{suffix}"
    meshio.write_mesh(path, v, f, vertex_normals=v - v.mean(0), vertex_colors=np.full(
        (len(v), 3), 0.5))
    v2, f2 = meshio.read_mesh(path)
    np.testing.assert_array_equal(v2, v)  # 17 digits / doubles: bit-exact
    np.testing.assert_array_equal(f2, f)
    assert v2.dtype == np.float64 and f2.dtype == np.int64
    v3, f3 = meshio.read_mesh(path.read_bytes(), suffix=suffix)
    np.testing.assert_array_equal(v3, v)
    np.testing.assert_array_equal(f3, f)


def test_stl_round_trip_float32(tmp_path):
    v, f = _mesh()
    path = tmp_path / "m.stl"
    meshio.write_mesh(path, v, f)
    v2, f2 = meshio.read_mesh(path)
    assert len(v2) == len(v) and len(f2) == len(f)  # shared vertices merged again
    assert _tri_set(v2, f2, 3) == _tri_set(v.astype(np.float32).astype(np.float64), f, 3)
    assert np.abs(np.sort(v2, axis=0) - np.sort(v, axis=0)).max() < 1e-7
    # binary STL layout: 80 + 4 + 50 per triangle
    assert path.stat().st_size == 84 + 50 * len(f)


def test_ply_mesh_normals_and_colours_readable_by_open3d(tmp_path):
    import open3d as o3d

    v, f = _mesh()
    nrm = (v - v.mean(0)) / np.linalg.norm(v - v.mean(0), axis=1, keepdims=True)
    col = np.random.default_rng(0).integers(0, 256, (len(v), 3)).astype(np.uint8)
    meshio.write_mesh(tmp_path / "m.ply", v, f, vertex_normals=nrm, vertex_colors=col)
    m = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    np.testing.assert_allclose(np.asarray(m.vertex_normals), nrm, atol=1e-7)
    np.testing.assert_allclose(np.asarray(m.vertex_colors) * 255, col, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(m.triangles), f)


def test_point_cloud_round_trip_with_attributes(tmp_path):
    rng = np.random.default_rng(1)
    p = rng.random((500, 3)) + [0.5, 0, 0]
    n = rng.normal(size=(500, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    attrs = {
        "sweep": np.repeat(np.arange(5), 100).astype(np.int64),
        "frame": np.arange(500, dtype=np.int64),
        "confidence": rng.random(500).astype(np.float32),
        "residual": rng.random(500),
        "valid": rng.random(500) > 0.5,
    }
    col = rng.random((500, 3))
    path = tmp_path / "c.ply"
    meshio.write_point_cloud(path, p, normals=n, colors=col, attributes=attrs)
    p2, n2 = meshio.read_point_cloud(path)
    np.testing.assert_array_equal(p2, p)
    np.testing.assert_allclose(n2, n, atol=1e-7)  # normals stored as float32
    got = meshio.read_point_cloud_attributes(path)
    assert set(got) == {"colors", "sweep", "frame", "confidence", "residual", "valid"}
    np.testing.assert_array_equal(got["sweep"], attrs["sweep"])
    assert got["sweep"].dtype == np.int32
    np.testing.assert_array_equal(got["frame"], attrs["frame"])
    np.testing.assert_array_equal(got["confidence"], attrs["confidence"])
    np.testing.assert_array_equal(got["residual"], attrs["residual"])
    np.testing.assert_array_equal(got["valid"].astype(bool), attrs["valid"])
    np.testing.assert_array_equal(got["colors"], np.round(col * 255).astype(np.uint8))
    header = path.read_bytes()[:400].decode("ascii", "replace")
    for line in ("property int sweep", "property float confidence",
                 "property double residual", "property uchar valid", "property uchar red"):
        assert line in header


def test_empty_cloud_and_mesh(tmp_path):
    meshio.write_point_cloud(tmp_path / "e.ply", np.zeros((0, 3)),
                             attributes={"sweep": np.zeros(0, dtype=int)})
    p, n = meshio.read_point_cloud(tmp_path / "e.ply")
    assert p.shape == (0, 3) and n is None
    assert meshio.read_point_cloud_attributes(tmp_path / "e.ply") == {}
    meshio.write_mesh(tmp_path / "e.ply", np.zeros((0, 3)), np.zeros((0, 3), dtype=int))
    v, f = meshio.read_mesh(tmp_path / "e.ply")
    assert v.shape == (0, 3) and f.shape == (0, 3)


def test_writes_are_atomic(tmp_path, monkeypatch):
    v, f = _mesh()
    target = tmp_path / "m.ply"
    meshio.write_mesh(target, v, f)
    before = target.read_bytes()

    def boom(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(meshio, "_write_ply", boom)
    with pytest.raises(OSError, match="disk full"):
        meshio.write_mesh(target, v + 1.0, f)
    assert target.read_bytes() == before  # the old file is intact
    assert sorted(x.name for x in tmp_path.iterdir()) == ["m.ply"]  # no temp file left
    with pytest.raises(OSError, match="disk full"):
        meshio.write_point_cloud(tmp_path / "new.ply", v)
    assert not (tmp_path / "new.ply").exists()


def test_bad_inputs(tmp_path):
    v, f = _mesh()
    with pytest.raises(ValueError, match="suffix|must end"):
        meshio.write_mesh(tmp_path / "m.vtk", v, f)
    with pytest.raises(ValueError, match="faces index"):
        meshio.write_mesh(tmp_path / "m.ply", v, f + len(v))
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        meshio.write_point_cloud(tmp_path / "c.ply", v[:, :2])
    with pytest.raises(ValueError, match="non-finite"):
        meshio.write_point_cloud(tmp_path / "c.ply", np.full((2, 3), np.nan))
    with pytest.raises(ValueError, match="clashes"):
        meshio.write_point_cloud(tmp_path / "c.ply", v, attributes={"red": np.zeros(len(v))})
    with pytest.raises(ValueError, match="int32"):
        meshio.write_point_cloud(tmp_path / "c.ply", v[:1],
                                 attributes={"t": np.array([2**40])})
    with pytest.raises(ValueError, match="shape"):
        meshio.write_point_cloud(tmp_path / "c.ply", v, attributes={"t": np.zeros(3)})
    with pytest.raises(ValueError, match="colors"):
        meshio.write_point_cloud(tmp_path / "c.ply", v, colors=np.full((len(v), 3), 2.0))
    with pytest.raises(FileNotFoundError):
        meshio.read_mesh(tmp_path / "missing.ply")
    with pytest.raises(FileNotFoundError):
        meshio.read_point_cloud(tmp_path / "missing.ply")
    with pytest.raises(StageError, match="cannot read mesh"):
        meshio.read_mesh(b"this is not a mesh", suffix=".ply")


def test_failed_read_keeps_the_working_directory(tmp_path):
    """pymeshlab moves the process into the file's folder when a load fails; read_mesh
    must leave the working directory where it was (its temporary folder is deleted)."""
    import os

    before = os.getcwd()
    with pytest.raises(StageError):
        meshio.read_mesh(b"this is not a mesh", suffix=".ply")
    assert os.getcwd() == before


def test_vertex_attributes_round_trip_and_errors(tmp_path):
    from robo3d.meshio import read_mesh, read_vertex_attributes, write_mesh

    rng = np.random.default_rng(0)
    v = rng.random((5, 3))
    f = np.array([[0, 1, 2], [0, 2, 3], [1, 3, 4]])
    attrs = {"source": np.array([0, 1, 2, 0, 1], np.uint8),
             "n_obs": np.array([3, 0, 0, 1, 70000], np.int64),
             "confidence": np.array([1.0, 0.0, 0.0, 0.5, 0.25], np.float32),
             "flag": np.array([True, False, True, False, True])}
    p = tmp_path / "m.ply"
    write_mesh(p, v, f, vertex_colors=np.full((5, 3), 200, np.uint8), attributes=attrs)
    back = read_vertex_attributes(p)
    assert set(back) == set(attrs)
    for k, a in attrs.items():
        np.testing.assert_array_equal(back[k], a.astype(back[k].dtype))
    assert back["source"].dtype == np.uint8 and back["n_obs"].dtype == np.int32
    V, F = read_mesh(p)  # other readers still read the mesh
    np.testing.assert_allclose(V, v)
    np.testing.assert_array_equal(F, f)
    with pytest.raises(ValueError, match="shape"):
        write_mesh(p, v, f, attributes={"source": np.zeros(4, np.uint8)})
    with pytest.raises(ValueError, match="reserved"):
        write_mesh(p, v, f, attributes={"x": np.zeros(5)})
    bad = tmp_path / "t.ply"
    # truncated in the faces: the vertices still read; truncated in the vertices: error
    bad.write_bytes(p.read_bytes()[:-10])
    assert set(read_vertex_attributes(bad)) == set(attrs)
    bad.write_bytes(p.read_bytes()[: p.read_bytes().index(b"end_header") + 20])
    with pytest.raises(ValueError, match="truncated"):
        read_vertex_attributes(bad)
    bad.write_bytes(b"solid x\n")
    with pytest.raises(ValueError, match="not a PLY"):
        read_vertex_attributes(bad)


def test_stl_and_obj_in_millimetres_and_files_readable_by_others(tmp_path):
    import os

    from robo3d.atomic import file_mode
    from robo3d.meshio import read_mesh, write_mesh

    v = np.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.05, 0.02]])
    f = np.array([[0, 1, 2]])
    for suffix in (".stl", ".obj", ".ply"):
        p = tmp_path / f"m_mm{suffix}"
        write_mesh(p, v, f, unit="mm")
        V, _ = read_mesh(p)
        np.testing.assert_allclose(V, v * 1000.0, rtol=1e-6)  # 100 mm long, as CAD reads it
        assert os.stat(p).st_mode & 0o777 == file_mode()  # not mkstemp's 0600
    assert "unit mm" in (tmp_path / "m_mm.obj").read_text().splitlines()[0]
    with pytest.raises(ValueError, match="unit"):
        write_mesh(tmp_path / "x.stl", v, f, unit="inch")


def test_npz_files_round_trip_at_the_fast_level(tmp_path):
    # robo3d.atomic.save_npz writes what np.savez_compressed does (np.load reads it back
    # exactly), deflated; an object array is refused, not pickled
    import zipfile

    from robo3d.atomic import save_npz

    rng = np.random.default_rng(3)
    arrays = {"points": rng.normal(size=(5000, 3)), "index": np.arange(5000, dtype=np.int32),
              "flags": rng.random(5000) < 0.5, "note": np.str_("{\"a\": 1}"),
              "empty": np.zeros((0, 3), dtype=np.float32)}
    path = tmp_path / "a.npz"
    save_npz(path, **arrays)
    with np.load(path, allow_pickle=False) as z:
        assert sorted(z.files) == sorted(arrays)
        for k, v in arrays.items():
            assert z[k].dtype == np.asarray(v).dtype
            np.testing.assert_array_equal(z[k], v)
    with zipfile.ZipFile(path) as zf:
        assert {i.compress_type for i in zf.infolist()} == {zipfile.ZIP_DEFLATED}
        assert zf.getinfo("points.npy").compress_size < zf.getinfo("points.npy").file_size
    with pytest.raises(ValueError):
        save_npz(tmp_path / "b.npz", bad=np.array([{"a": 1}], dtype=object))
    assert not (tmp_path / "b.npz").exists()
