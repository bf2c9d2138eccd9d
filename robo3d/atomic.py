"""Atomic file output: a killed or failed job never leaves a file that looks complete.

Every writer in robo3d writes to a temporary file beside its target and renames it into
place only when the content is complete (``os.replace`` is atomic on POSIX file systems).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_path", "write_json", "save_npz", "json_default", "dumps_json", "file_mode",
           "dir_mode"]


def _process_umask() -> int:
    """The process's umask (read once: setting it back at once is the only way to read it)."""
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


_UMASK = _process_umask()


def file_mode() -> int:
    """The mode a new file gets from ``open()``: 0666 less the process's umask (0644 with
    the usual 022), so that other users of a shared cell can read the results."""
    return 0o666 & ~_UMASK


def dir_mode() -> int:
    """The mode a new folder gets from ``mkdir``: 0777 less the umask (0755 with 022)."""
    return 0o777 & ~_UMASK


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` if the block succeeds,
    remove it if the block raises. The temporary name keeps the target's suffix so that
    libraries choosing a format by extension (Open3D, pymeshlab) still do. The file gets
    the mode an ordinary ``open()`` would give it (:func:`file_mode`), not ``mkstemp``'s
    0600."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.stem}.", suffix=f".tmp{target.suffix}",
                               dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.chmod(tmp_path, file_mode())
        os.replace(tmp_path, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp_path.unlink()
        raise


def json_default(obj: Any) -> Any:
    """``json.dump``'s ``default``, the one every robo3d JSON writer uses: numpy scalars
    and arrays become Python numbers and lists, paths strings, sets sorted lists.
    Anything else is a ``TypeError``: a report that holds some other object is a bug to
    see, not a ``repr`` to write."""
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    if isinstance(obj, set | frozenset):
        return sorted(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def dumps_json(data: Any) -> str:
    """``data`` as indented JSON text (:func:`json_default` converts numpy and paths;
    NaN stays NaN as Python's ``json`` writes it)."""
    return json.dumps(data, indent=2, sort_keys=False, default=json_default, allow_nan=True)


def write_json(path: str | os.PathLike[str], data: Any) -> None:
    """Write ``data`` as indented JSON (:func:`dumps_json`), atomically."""
    text = dumps_json(data)
    with atomic_path(path) as tmp, open(tmp, "w", encoding="utf-8") as f:
        f.write(text + "\n")


#: zlib level of the .npz files: float arrays of measurements barely compress beyond what
#: level 1 gets (issue 11's cup/7: clouds.npz 18.5 MB at 1, 18.3 MB at numpy's default 6),
#: and level 6 took 0.83 s against 0.51 s to write it
NPZ_COMPRESSLEVEL = 1


def save_npz(path: str | os.PathLike[str], **arrays: Any) -> None:
    """The arrays as a compressed ``.npz`` (what ``np.savez_compressed`` writes, read by
    ``np.load``, at zlib level :data:`NPZ_COMPRESSLEVEL`) to ``path``, atomically."""
    import zipfile

    with atomic_path(path) as tmp:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED,
                             compresslevel=NPZ_COMPRESSLEVEL, allowZip64=True) as zf:
            for key, value in arrays.items():
                with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.asanyarray(value), allow_pickle=False)
