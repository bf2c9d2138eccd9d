"""The workflow's side of the library: which recordings a batch holds, which config
sections each stage reads, and running one stage from a Snakemake rule.

- :func:`find_recordings` turns the config's ``recordings`` (a folder or a list) into
  the batch, and says what a folder held when it yields no recording;
  :func:`split_by_kind` parts it into scans and ``kind=calibration`` recordings, and
  :func:`scan_calibrations` says which calibration each scan uses (``scan_calibration``).
- :data:`STAGE_CONFIG` / :func:`stage_config`: the config sections of each stage, the
  rules' ``params:`` (a changed parameter re-runs exactly the stages that read it), with
  :func:`code_version` (a hash of the library's code: an upgrade re-runs too).
- :func:`run_from_snakemake`: a rule's script in one call: logging to the job's log and
  the terminal, stale temporaries removed, Open3D pinned to one thread where a stage runs
  it (:func:`robo3d.stages.common.pin_open3d_threads`), a robo3d error as one clear line.

The stages themselves live in :mod:`robo3d.stages` (one module per rule, re-exported here
as ``stage_<name>``); the artefacts they hand each other in :mod:`robo3d.artefacts`.
"""

from __future__ import annotations

import logging
import os
import re
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .errors import Robo3dError
from .stages.align import stage_align
from .stages.calibrate import stage_calibrate
from .stages.carve import stage_carve
from .stages.common import OPEN3D_STAGES, code_version, log, pin_open3d_threads, topic_map
from .stages.evaluate import stage_evaluate
from .stages.foxglove import stage_foxglove
from .stages.fuse import stage_fuse
from .stages.pictures import stage_pictures
from .stages.silhouettes import stage_silhouettes
from .stages.simplify import stage_simplify
from .stages.stripes import stage_stripes
from .stages.triangulate import stage_triangulate

__all__ = [
    "RecordingEntry",
    "find_recordings",
    "split_by_kind",
    "recording_kind",
    "scan_calibrations",
    "export_library_path",
    "machine_memory_mb",
    "recording_stages",
    "topic_map",
    "stage_silhouettes",
    "stage_carve",
    "stage_stripes",
    "stage_triangulate",
    "stage_align",
    "stage_fuse",
    "stage_simplify",
    "stage_evaluate",
    "stage_pictures",
    "stage_foxglove",
    "stage_calibrate",
    "STAGES",
    "STAGE_CONFIG",
    "stage_config",
    "code_version",
    "run_from_snakemake",
    "RUN_DETAIL_KEYS",
    "without_run_details",
]


# ---------------------------------------------------------------------------- batch
@dataclass
class RecordingEntry:
    """One recording of a batch: its name (results/<name>/), its file and what it holds."""

    name: str
    path: str
    summary: Any = None  # robo3d.recording.reader.RecordingSummary, probed lazily
    _topics: dict[str, str] = field(default_factory=dict)


def find_recordings(spec: str | list[str], topics: Mapping[str, str] | None = None,
                    kind: str | None = None) -> dict[str, RecordingEntry]:
    """The recordings of a batch: every ``*.mcap`` in a folder, or a list of files.

    ``kind`` = ``"scan"`` or ``"calibration"`` keeps only those (:func:`split_by_kind`);
    None keeps every recording.

    A rosbag2 directory (``metadata.yaml`` beside an ``.mcap``) counts as one recording
    named after the directory, and so does a sub-folder holding ``<folder>_0.mcap`` without
    ``metadata.yaml`` (a bag whose recorder died before writing it: the reader reads what
    is there and says what is missing). Names must be unique (they name
    ``results/<name>/``).
    """
    from .errors import ConfigError

    paths: list[Path] = []
    items = [spec] if isinstance(spec, str) else list(spec)
    for item in items:
        p = Path(item)
        if p.is_dir():
            if _is_bag_dir(p):
                paths.append(p)
            else:
                paths += sorted(p.glob("*.mcap"))
                paths += sorted(d for d in p.iterdir() if d.is_dir() and _is_bag_dir(d))
        elif p.exists():
            paths.append(p)
        else:
            raise ConfigError(f"config key recordings: {item} does not exist")
    if not paths:
        raise ConfigError(f"config key recordings: no recording in {', '.join(map(str, items))}"
                          f" ({_what_is_there(items)}); robo3d reads MCAP files (*.mcap) "
                          "and rosbag2 folders holding them")
    out: dict[str, RecordingEntry] = {}
    for p in paths:
        name = p.stem if p.is_file() else p.name
        if name in out:
            raise ConfigError(f"config key recordings: two recordings named {name!r} "
                              f"({out[name].path} and {p}); results/<name>/ must be unique")
        out[name] = RecordingEntry(name, str(p), None, dict(topics or {}))
    if kind is not None:
        if kind not in ("scan", "calibration"):
            raise ValueError(f"kind must be scan, calibration or None, got {kind!r}")
        return split_by_kind(out)[0 if kind == "scan" else 1]
    return out


def recording_kind(entry: RecordingEntry) -> str:
    """``calibration`` for a recording whose metadata says ``kind=calibration``, else
    ``scan`` (an unreadable file too: its scan jobs fail with the reader's message)."""
    if entry.summary is None:
        from .recording.reader import probe_recording

        entry.summary = probe_recording(entry.path, topic_map(entry._topics))
    return "calibration" if getattr(entry.summary, "kind", None) == "calibration" else "scan"


def split_by_kind(entries: Mapping[str, RecordingEntry]
                  ) -> tuple[dict[str, RecordingEntry], dict[str, RecordingEntry]]:
    """The scans and the calibration recordings of a batch (``robo3d.recording`` metadata
    ``kind``, read by the cheap probe). Calibrations make ``results/calibration/<name>``,
    so a scan may not be named ``calibration``."""
    from .errors import ConfigError

    scans = {n: e for n, e in entries.items() if recording_kind(e) == "scan"}
    calibs = {n: e for n, e in entries.items() if n not in scans}
    if "calibration" in scans:
        raise ConfigError(f"config key recordings: a scan named 'calibration' "
                          f"({scans['calibration'].path}) would write into "
                          "results/calibration/, where the calibrations go; rename it")
    return scans, calibs


def scan_calibrations(setting: str | Mapping[str, str | None] | None,
                      scans: Mapping[str, Any], calibrations: Mapping[str, Any]
                      ) -> dict[str, str | None]:
    """Which calibration each scan uses (config key ``scan_calibration``): a name for every
    scan, or None where the scan keeps the calibration it carries.

    Raises
    ------
    ConfigError
        A calibration name that is not among the batch's calibration recordings, or a scan
        name that is not among its scans, naming what there is.
    """
    from .errors import ConfigError

    def known(name: str, where: str) -> str:
        if name not in calibrations:
            have = ", ".join(sorted(calibrations)) or "none (no kind=calibration recording " \
                "among the recordings)"
            raise ConfigError(f"config key {where}: no calibration recording named {name!r}; "
                              f"calibration recordings: {have}")
        return name

    if setting is None:
        return {s: None for s in scans}
    if isinstance(setting, str):
        return {s: known(setting, "scan_calibration") for s in scans}
    unknown = sorted(set(setting) - set(scans))
    if unknown:
        raise ConfigError(f"config key scan_calibration: {', '.join(map(repr, unknown))} "
                          f"{'is not a scan' if len(unknown) == 1 else 'are not scans'} of "
                          f"the batch; scans: {', '.join(sorted(scans)) or 'none'}")
    return {s: (known(setting[s], f"scan_calibration.{s}") if setting.get(s) else None)
            for s in scans}


def _what_is_there(items: list[str]) -> str:
    """What the folders of a recordings list hold instead of recordings, in words."""
    from collections import Counter

    files = [f for it in items if Path(it).is_dir() for f in Path(it).rglob("*")
             if f.is_file()][:10000]
    if not files:
        return "it is empty" if len(items) == 1 else "they are empty"
    kinds = Counter(f.suffix.lower() or "(no suffix)" for f in files)
    found = ", ".join(f"{n} {k}" for k, n in kinds.most_common(5))
    hint = ""
    if ".db3" in kinds:
        hint = ("; .db3 files are ROS 2 bags in SQLite: convert them to MCAP with "
                "`ros2 bag convert` (storage_id mcap)")
    elif ".bag" in kinds:
        hint = "; .bag files are ROS 1 bags: convert them with `mcap convert`"
    return f"found {found}{hint}"


def _is_bag_dir(d: Path) -> bool:
    """A rosbag2 directory: its ``metadata.yaml``, or (recorder died) ``<dir>_0.mcap``."""
    return (d / "metadata.yaml").exists() or (d / f"{d.name}_0.mcap").exists()


def recording_stages(entry: RecordingEntry) -> set[str]:
    """Which halves of the pipeline a recording supports: ``hull`` (silhouette views) and
    ``laser`` (laser frames). An unreadable file gets both, so that its jobs run and fail
    with the reader's message while the rest of the batch goes on."""
    if entry.summary is None:
        from .recording.reader import probe_recording

        entry.summary = probe_recording(entry.path, topic_map(entry._topics))
    s = entry.summary
    if not getattr(s, "readable", True):
        return {"hull", "laser"}
    out = set()
    if s.n_views > 0:
        out.add("hull")
    if s.n_laser_frames > 0:
        out.add("laser")
    return out


def has_workspace_box(entry: RecordingEntry) -> bool:
    """Whether a recording's metadata gives its workspace box (``robo3d.recording``:
    ``workspace_min`` and ``workspace_max``). Without one the align stage takes the
    visual hull's box (``alignment.workspace_from_hull``) and so needs the hull."""
    recording_stages(entry)  # probes the file once
    meta = (getattr(entry.summary, "metadata", None) or {}).get("robo3d.recording") or {}
    return "workspace_min" in meta and "workspace_max" in meta


def export_library_path(repo_root: str) -> None:
    """Put the checkout on ``PYTHONPATH`` so that every job imports this robo3d, also in
    ``--use-conda`` environments that install only the dependencies."""

    parts = [str(repo_root)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                if p and p != str(repo_root)]
    os.environ["PYTHONPATH"] = os.pathsep.join(parts)


def machine_memory_mb() -> int:
    """This machine's physical memory in MB: on a local run, the jobs that run at once
    declare no more memory (``resources: mem_mb``) than this."""
    return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE") // 1_000_000


STAGES: dict[str, Callable[..., dict[str, Any]]] = {
    "silhouettes": stage_silhouettes,
    "carve": stage_carve,
    "stripes": stage_stripes,
    "triangulate": stage_triangulate,
    "align": stage_align,
    "fuse": stage_fuse,
    "simplify": stage_simplify,
    "evaluate": stage_evaluate,
    "pictures": stage_pictures,
    "foxglove": stage_foxglove,
    "calibrate": stage_calibrate,
}


class _TerminalFilter(logging.Filter):
    """What a job shows on the terminal: its stage's summary and progress lines
    (``robo3d.summary``) and every warning or error; the log file keeps everything."""

    def filter(self, record: logging.LogRecord) -> bool:
        return record.name == "robo3d.summary" or record.levelno >= logging.WARNING


def _setup_logging(log_path: str | None, rec: str = "", stage: str = "") -> None:
    fmt = logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s", "%H:%M:%S")
    where = " ".join(x for x in (rec, stage) if x)
    term = logging.Formatter(f"%(asctime)s {where}: %(message)s" if where else
                             "%(asctime)s %(message)s", "%H:%M:%S")
    root = logging.getLogger()
    root.setLevel(logging.INFO)
    for h in list(root.handlers):
        root.removeHandler(h)
    err = logging.StreamHandler(sys.stderr)
    err.setFormatter(term)
    err.addFilter(_TerminalFilter())
    root.addHandler(err)
    if log_path:
        Path(log_path).parent.mkdir(parents=True, exist_ok=True)
        fh = logging.FileHandler(log_path, mode="w", encoding="utf-8")
        fh.setFormatter(fmt)
        root.addHandler(fh)


#: The config sections each stage reads (its rule passes them as ``params``, so that
#: changing one re-runs exactly the stages that read it, and those after them).
STAGE_CONFIG: dict[str, tuple[str, ...]] = {
    "silhouettes": ("segmentation", "carving", "triangulation", "alignment", "topics", "frames",
                    "timing", "rerun", "seed"),
    "carve": ("carving", "topics", "frames", "timing", "rerun", "seed"),
    "stripes": ("stripes", "triangulation", "topics", "frames", "timing", "rerun", "seed"),
    "triangulate": ("triangulation", "topics", "frames", "timing", "rerun", "seed"),
    "align": ("alignment", "triangulation", "topics", "frames", "timing", "rerun", "seed"),
    "fuse": ("fusion", "triangulation", "carving", "rerun", "seed"),
    "simplify": ("simplify", "rerun", "seed"),
    "evaluate": ("evaluation", "fusion", "topics", "frames", "timing", "rerun", "seed"),
    "pictures": ("report", "evaluation", "topics", "frames", "timing"),
    "foxglove": ("foxglove", "frames"),
    "calibrate": ("calibration", "laser_sheet", "stripes", "calibration_gates", "topics",
                  "frames", "timing", "seed"),
}


def _stage_config_keys() -> dict[str, dict[str, tuple[str, ...]]]:
    """Sections a stage reads only in part: per stage, section -> the keys it reads."""
    from .silhouettes import LASER_ALIGNMENT_KEYS, LASER_TRIANGULATION_KEYS, RESEGMENT_CARVING_KEYS

    return {"silhouettes": {"carving": RESEGMENT_CARVING_KEYS,
                            "triangulation": LASER_TRIANGULATION_KEYS,
                            "alignment": LASER_ALIGNMENT_KEYS}}


def stage_config(cfg: Mapping[str, Any], stage: str) -> dict[str, Any]:
    """The part of the (validated) config that ``stage`` reads (:data:`STAGE_CONFIG`; of a
    section it reads in part, only those keys)."""
    out = {k: cfg[k] for k in STAGE_CONFIG[stage] if k in cfg}
    for section, keys in _stage_config_keys().get(stage, {}).items():
        if isinstance(out.get(section), Mapping):
            out[section] = {k: out[section][k] for k in keys if k in out[section]}
    return out


#: the keys of metrics.json (at any depth) that describe the run, not the scan: wall-clock
#: and CPU times, frames per second, the threads a stage was given
RUN_DETAIL_KEYS = re.compile(r"seconds|(^|_)time_s$|(^|_)fps$|^timings$|^threads$")


def without_run_details(metrics: Any) -> Any:
    """``metrics`` (a run's metrics.json) without its :data:`RUN_DETAIL_KEYS`: what two
    runs of the same recording and config must agree on exactly, whatever the machine
    and the number of cores."""
    if isinstance(metrics, dict):
        return {k: without_run_details(v) for k, v in metrics.items()
                if not RUN_DETAIL_KEYS.search(str(k))}
    if isinstance(metrics, list):
        return [without_run_details(v) for v in metrics]
    return metrics


def run_from_snakemake(stage: str, smk: Any) -> None:
    """Run one stage from a Snakemake ``script:`` job (``smk`` is the injected object).

    A robo3d error (bad input, a stage that cannot produce its result) is logged as one
    clear line and ends the job with exit status 1, without a traceback from deep inside a
    library; any other exception (a bug) is logged with its traceback, so that the job's
    log always says why it failed (``robo3d status`` reads the first error line).
    Snakemake then removes the job's outputs and, with ``--keep-going``, finishes the
    other recordings. Temporary files that a killed earlier attempt left beside the
    outputs (``.<name>.*.tmp<suffix>``, never mistaken for outputs) are removed first.
    A stage that takes ``threads`` gets the job's; one that takes ``has_laser`` the rule's
    ``params.has_laser``.
    """
    import inspect

    rec = smk.wildcards.get("rec") or smk.wildcards.get("calib") or "recording"
    _setup_logging(smk.log[0] if len(smk.log) else None, rec, stage)
    inputs = {k: str(v) for k, v in smk.input.items()}
    outputs = {k: str(v) for k, v in smk.output.items()}
    _remove_stale_temporaries(outputs.values())
    fn = STAGES[stage]
    kwargs = {}
    if "threads" in inspect.signature(fn).parameters and getattr(smk, "threads", None):
        kwargs["threads"] = int(smk.threads)
    if "has_laser" in inspect.signature(fn).parameters and hasattr(
            getattr(smk, "params", None), "has_laser"):
        kwargs["has_laser"] = bool(smk.params.has_laser)
    # the rule's params hold the sections this stage reads (what triggers its re-runs);
    # the stage sees only those, so a section it reads but does not declare is a bug
    params = getattr(smk, "params", None)
    cfg = params.cfg if params is not None and hasattr(params, "cfg") else smk.config
    if stage in OPEN3D_STAGES:  # byte-identical results whatever the thread timing
        pin_open3d_threads()
    from .deferred import keep_pandas_out

    keep_pandas_out()  # pyarrow's probe for pandas objects, 0.27 s per job (robo3d.deferred)
    try:
        fn(inputs, outputs, cfg, rec, **kwargs)
    except Robo3dError as exc:
        log.error("%s failed for %s: %s", stage, rec, exc)
        logging.shutdown()
        sys.exit(1)
    except KeyboardInterrupt:  # Ctrl-C: say so, then die by the signal as expected
        import os
        import signal

        log.error("%s for %s interrupted; its outputs were not written", stage, rec)
        logging.shutdown()
        signal.signal(signal.SIGINT, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGINT)
    except Exception as exc:
        log.exception("%s failed for %s with an unexpected %s: %s (a bug in robo3d: please "
                      "report it with this log)", stage, rec, type(exc).__name__, exc)
        logging.shutdown()
        sys.exit(1)


def _remove_stale_temporaries(outputs: Iterable[str]) -> list[Path]:
    """Delete what killed jobs left of :func:`robo3d.atomic.atomic_path`'s temporaries of
    these outputs (and of mask folders); returns the paths removed."""
    import shutil

    removed = []
    for out in outputs:
        target = Path(out)
        if not target.parent.is_dir():
            continue
        patterns = (f".{target.stem}.*.tmp{target.suffix}", f".{target.name}.*")
        for pattern in patterns:
            for p in target.parent.glob(pattern):
                if p.is_dir():
                    shutil.rmtree(p, ignore_errors=True)
                else:
                    p.unlink(missing_ok=True)
                removed.append(p)
    if removed:
        log.info("removed %d temporary files left by an earlier, killed attempt: %s",
                 len(removed), ", ".join(p.name for p in removed))
    return removed
