"""Open3D's plotly viewer imported on first use, not with Open3D.

``import open3d`` (0.20) imports ``open3d.visualization.draw_plotly``, which imports
plotly and dash, a web-app framework: 0.3 of the 0.6 s that ``import open3d`` takes on
the machine of ``benchmarks/README.md`` (stop 47), in every job of the workflow (most
of them read or write a mesh or a cloud through Open3D), and robo3d never draws with
plotly. :func:`defer_open3d_plotly`, called when ``robo3d`` is imported, puts a stand-in
for that module in ``sys.modules`` before Open3D is imported: Open3D's
``from .draw_plotly import get_plotly_fig`` then binds functions that load the real
module (and plotly and dash) the first time one of them is called, so a user's own
``open3d.visualization.draw_plotly(...)`` in a process that imported robo3d still works.
Nothing is done when Open3D is already imported.

:func:`keep_pandas_out` is for the workflow's stage processes only
(:func:`robo3d.pipeline.run_from_snakemake`): pyarrow (under rerun) tries to import
pandas at its first Arrow conversion, to know whether what it converts is a pandas
object, and pandas takes 0.27 s to import (stop 48), in every job, wherever pandas is
installed (the test extras' SLURM plugin brings it). No stage hands pandas objects to
pyarrow, so there a failed import is the right answer, and cheap.
"""

from __future__ import annotations

import importlib.util
import sys
import types
from collections.abc import Callable
from typing import Any

_NAME = "open3d.visualization.draw_plotly"


def _real() -> types.ModuleType:
    """The real module, loaded from Open3D's package on first use (replacing the
    stand-in in ``sys.modules``)."""
    mod = sys.modules.get(_NAME)
    if mod is not None and not getattr(mod, "_robo3d_deferred", False):
        return mod
    import open3d.visualization as vis

    spec = importlib.util.spec_from_file_location(
        _NAME, vis.__file__.replace("__init__.py", "draw_plotly.py"))
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot find {_NAME} in {vis.__file__}")
    real = importlib.util.module_from_spec(spec)
    sys.modules[_NAME] = real
    try:
        spec.loader.exec_module(real)
    except BaseException:
        sys.modules[_NAME] = mod  # the stand-in again: a later call tries again
        raise
    return real


def _deferred(name: str) -> Callable[..., Any]:
    def call(*args: Any, **kwargs: Any) -> Any:
        return getattr(_real(), name)(*args, **kwargs)

    call.__name__ = call.__qualname__ = name
    call.__doc__ = f"{_NAME}.{name}, loaded on first call (robo3d.deferred)."
    return call


def _stand_in_attr(name: str) -> Any:
    if name.startswith("__"):
        raise AttributeError(name)
    return _deferred(name)


def defer_open3d_plotly() -> bool:
    """Put the stand-in for Open3D's plotly viewer in ``sys.modules`` unless Open3D (or
    that module) is imported already; True when it did."""
    if "open3d" in sys.modules or _NAME in sys.modules:
        return False
    stand_in = types.ModuleType(_NAME, "Open3D's plotly viewer, loaded on first use "
                                       "(robo3d.deferred)")
    stand_in._robo3d_deferred = True  # type: ignore[attr-defined]
    stand_in.__getattr__ = _stand_in_attr  # type: ignore[method-assign]
    sys.modules[_NAME] = stand_in
    return True


class _NoPandas:
    """A meta path finder that refuses ``pandas`` (:func:`keep_pandas_out`)."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> None:
        if name == "pandas" or name.startswith("pandas."):
            raise ModuleNotFoundError(
                f"{name} is kept out of robo3d's workflow jobs (robo3d.deferred."
                "keep_pandas_out: pyarrow would import it at its first conversion)",
                name=name)
        return None


def keep_pandas_out() -> bool:
    """Make ``import pandas`` fail in this process (a workflow stage's), so that pyarrow's
    probe for pandas objects costs a failed import instead of importing pandas; True
    when it did. Nothing is done when pandas is imported already."""
    if "pandas" in sys.modules or any(isinstance(f, _NoPandas) for f in sys.meta_path):
        return False
    sys.meta_path.insert(0, _NoPandas())
    return True
