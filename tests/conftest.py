"""Shared test session setup: numba's kernels compiled on the second core.

A fresh clone (CI) has no numba cache (``robo3d/__pycache__/*.nbi, *.nbc``; an edit of a
module invalidates its entries too), and the first call of each numba kernel with each
image type compiles it. The stripe detector's kernels cost most: measured on this 2-core
machine, 94 s of CPU for the first 8-bit mono frame, and tens of seconds more for each of
float32, 16-bit and RGB images, which only some tests use (a float32 frame's kernels load
from the cache in 0.6 s of CPU). The suite runs in one process,
mostly on one core; so when the selected tests include the stripe tests and other tests
run before them, a second process compiles those kernels for the image types the later
tests use (float32, 16-bit, RGB first, the 8-bit mono frames that the first tests compile
themselves last), plus the octree and triangulation kernels, and writes them to numba's
on-disk cache. A test's own call then loads the compiled kernel from the cache instead
of compiling it (numba reads the cache index at every compilation). Nothing a test
computes or asserts changes: the cache holds the same machine code the test would
compile. The process is ended when the session ends; ``ROBO3D_TEST_NO_WARMUP=1`` turns
it off (e.g. to time the suite without it).

Under pytest-xdist (``./run.sh test`` runs two workers, one test file per worker at a
time) both cores are the tests' own, so there is no warm-up process here: ``./run.sh
test`` runs ``robo3d warm-up --all-types`` before pytest (the 8-bit kernels, which the
end-to-end tests' many jobs would otherwise each compile at once, and on the second core
the 16-bit and float frames' and the other methods', which the stripe tests would
compile one after another); instead the longest files
(the end-to-end workflow runs, minutes each) are handed out first, so that they run
beside the many short files instead of after them.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

#: What the background process runs: :mod:`robo3d.warmup`'s parts, the image types and
#: methods the later tests use first (``robo3d warm-up --all-types``), the 8-bit frames
#: that the first tests compile themselves last. Least niceness priority: it only uses a
#: core the tests leave idle.
WARM_UP = r"""
import os
os.nice(10)
from robo3d import warmup
warmup._stripes_other(True)
warmup._stripes_other(False)
warmup.compile_kernels(1)
"""

#: Test modules that call the stripe detector with image types the first tests do not.
_LATER_USERS = ("test_stripes.py",)

_warm: subprocess.Popen | None = None


def pytest_collection_finish(session: pytest.Session) -> None:
    global _warm
    if (os.environ.get("ROBO3D_TEST_NO_WARMUP") or session.config.option.collectonly
            or os.environ.get("PYTEST_XDIST_WORKER")):
        return
    names = [item.path.name for item in session.items]
    first = next((i for i, n in enumerate(names) if n in _LATER_USERS), None)
    if not first:  # no stripe tests, or they come first: nothing to overlap
        return
    _warm = subprocess.Popen([sys.executable, "-c", WARM_UP], stdout=subprocess.DEVNULL,
                             stderr=subprocess.DEVNULL)


#: The files that take longest, longest first (seconds on a 2-core Intel Xeon, stop 44,
#: the two first side by side: workflow 160 + 35, slurm 188, the failed silhouettes 42,
#: resume 36, then simplify); the others follow in collection order. The stripe tests
#: were here while they compiled their kernels (``robo3d warm-up --all-types`` now does).
_LONGEST_FIRST = ("test_workflow.py", "test_slurm.py", "test_workflow_failed_silhouettes.py",
                  "test_resume.py", "test_simplify.py", "test_fusion.py",
                  "test_alignment_property.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under xdist, the longest files first (stable order otherwise): xdist's ``loadfile``
    schedule hands out files in collection order (``./run.sh test`` passes
    ``--no-loadscope-reorder``: xdist's own reorder, by number of tests per file, handed the
    two-test SLURM file out near the end, where it ran alone on one core for minutes)."""
    if not os.environ.get("PYTEST_XDIST_WORKER"):
        return
    rank = {name: i for i, name in enumerate(_LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    global _warm
    if _warm is not None and _warm.poll() is None:
        _warm.terminate()
        try:
            _warm.wait(timeout=10)
        except subprocess.TimeoutExpired:
            _warm.kill()
            _warm.wait()
    _warm = None
