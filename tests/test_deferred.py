"""Open3D's plotly viewer is not imported with robo3d and Open3D, and still works when
called (robo3d.deferred)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from robo3d.deferred import defer_open3d_plotly

_CHILD = """
import sys
import numpy as np
import robo3d, open3d
assert "dash" not in sys.modules and "plotly" not in sys.modules, "imported with open3d"
pc = open3d.geometry.PointCloud(open3d.utility.Vector3dVector(np.random.rand(20, 3)))
fig = open3d.visualization.get_plotly_fig([pc])
assert type(fig).__name__ == "Figure", type(fig)
assert "dash" in sys.modules and "plotly" in sys.modules
real = sys.modules["open3d.visualization.draw_plotly"]
assert not getattr(real, "_robo3d_deferred", False) and hasattr(real, "get_point_object")
print("ok")
"""


def test_open3d_imported_after_robo3d_leaves_plotly_and_dash_until_called():
    out = subprocess.run([sys.executable, "-c", _CHILD], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_nothing_is_done_once_open3d_is_imported():
    import open3d  # noqa: F401

    assert defer_open3d_plotly() is False


_NO_PANDAS_CHILD = """
import sys
import numpy as np
from robo3d.deferred import keep_pandas_out
assert keep_pandas_out() is True and keep_pandas_out() is False
import rerun as rr
rec = rr.RecordingStream("robo3d_test")
rr.log("points", rr.Points3D(np.zeros((3, 3))), recording=rec)
rr.log("base", rr.ViewCoordinates.RDF, static=True, recording=rec)
assert "pandas" not in sys.modules, "pyarrow imported pandas"
try:
    import pandas  # noqa: F401
except ModuleNotFoundError as exc:
    assert "keep_pandas_out" in str(exc), exc
else:
    raise AssertionError("pandas was imported")
print("ok")
"""


def test_a_stage_process_logs_to_rerun_without_importing_pandas():
    import importlib.util

    if importlib.util.find_spec("pandas") is None:
        pytest.skip("pandas is not installed here: nothing to keep out")
    out = subprocess.run([sys.executable, "-c", _NO_PANDAS_CHILD], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_pandas_already_imported_is_left_alone():
    out = subprocess.run([sys.executable, "-c",
                          "import pandas, sys\nfrom robo3d.deferred import keep_pandas_out\n"
                          "assert keep_pandas_out() is False\n"
                          "assert not any(type(f).__name__ == '_NoPandas' "
                          "for f in sys.meta_path)\nprint('ok')"],
                         capture_output=True, text=True, timeout=120)
    if "No module named 'pandas'" in out.stderr:
        pytest.skip("pandas is not installed here")
    assert out.returncode == 0, out.stderr


_NO_NUMBA_CHILD = """
import sys
from robo3d.pipeline import run_from_snakemake  # what every workflow job imports
import robo3d.fusion, robo3d.simplify, robo3d.evaluate, robo3d.silhouettes, robo3d.viz
import robo3d.transforms, robo3d.camera
print("numba" in sys.modules)
"""


def test_stages_without_compiled_kernels_do_not_import_numba():
    # numba costs 0.2-0.5 s of every job's start; only the stripes, triangulation,
    # carving and alignment use it, and they import it themselves
    out = subprocess.run([sys.executable, "-c", _NO_NUMBA_CHILD], capture_output=True,
                         text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"
    out = subprocess.run([sys.executable, "-c", "import sys, robo3d.registration\n"
                          "print('numba' in sys.modules)"], capture_output=True, text=True,
                         timeout=120)
    assert out.stdout.strip() == "True", out.stderr  # the check above can see numba
