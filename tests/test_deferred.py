"""Open3D's plotly viewer is not imported with robo3d and Open3D, and still works when
called (robo3d.deferred)."""

from __future__ import annotations

import subprocess
import sys

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
