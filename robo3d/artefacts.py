"""The typed artefacts that the stages hand each other, each with its own save and load.

One place for what a stage writes and the next reads, so that a file's layout is defined
once: the silhouettes (``silhouettes.npz``), the visual hull (``hull.npz``, a
:class:`~robo3d.grid.VoxelGrid`), the stripes (``stripes.npz``) and the sweep clouds
(``clouds.npz``, ``aligned.npz``). Every save is atomic (:mod:`robo3d.atomic`); every load
checks what it reads and names the file when something is missing or malformed.
"""

from __future__ import annotations

# --- silhouettes (silhouettes.npz) ---------------------------------------------------

# --- visual hull (hull.npz) ----------------------------------------------------------

# --- stripes (stripes.npz) -----------------------------------------------------------

# --- sweep clouds (clouds.npz, aligned.npz) ------------------------------------------
