"""robo3d: measured 3D models from a robot-carried camera and line laser."""

from .deferred import defer_open3d_plotly as _defer_open3d_plotly

__version__ = "0.1.0"

# Open3D's plotly viewer (plotly and dash: half of `import open3d`'s time) is loaded
# only if something calls it (robo3d.deferred)
_defer_open3d_plotly()
