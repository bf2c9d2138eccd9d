# Validation and the small helpers the rules use. Logic lives in robo3d/, not here.
import sys

from robo3d.config import validate_config
from robo3d.info import finished_recordings
from robo3d.pipeline import (
    code_version,
    export_library_path,
    find_recordings,
    has_workspace_box,
    machine_memory_mb,
    recording_stages,
    scan_calibrations,
    split_by_kind,
    stage_config,
)

config.update(validate_config(config))

export_library_path(workflow.basedir)

# A local run keeps the declared memory (each rule's resources: mem_mb) of the jobs it runs
# at once within this machine's memory; --resources mem_mb=N sets another budget. On a
# cluster (--executor slurm) the scheduler packs the jobs on its nodes instead.
if workflow.global_resources["_nodes"].value is None:
    workflow.global_resources.setdefault("mem_mb", machine_memory_mb())

# the scans, and the kind=calibration recordings (each makes results/calibration/<calib>.yaml)
RECORDINGS, CALIBRATIONS = split_by_kind(find_recordings(config["recordings"],
                                                         topics=config["topics"]))
# the calibration each scan uses instead of its own (config scan_calibration), or None
SCAN_CALIBRATION = scan_calibrations(config["scan_calibration"], RECORDINGS, CALIBRATIONS)
CODE_VERSION = code_version()


def stage_threads(wanted):
    """Threads of a stage that can use several (stripes, carve, fuse): what it wants while
    the recordings are fewer than the cores, else one each. A batch fills the cores with
    recordings instead: these stages use about one core on small scans while holding two,
    and holding two kept the other recordings' jobs waiting (20 small recordings on 2
    cores ran at 1.23x one core's throughput before, 2.06x after: benchmarks/results/
    batch.json). The results do not depend on the number of threads
    (benchmarks/results/determinism.json)."""
    cores = workflow.cores or wanted
    return max(1, min(int(wanted), int(cores) // max(1, len(RECORDINGS))))


def stage_params(stage):
    """A rule's params: the config sections its stage reads and robo3d's code version;
    a change to either re-runs the rule (and what depends on its outputs)."""
    return {"cfg": stage_config(config, stage), "code": CODE_VERSION}


wildcard_constraints:
    rec="|".join(sorted(RECORDINGS)) or "NO_RECORDINGS",
    calib="|".join(sorted(CALIBRATIONS)) or "NO_CALIBRATIONS",


def get_recording(wildcards):
    """The .mcap file of one recording."""
    return RECORDINGS[wildcards.rec].path


def has_laser(wildcards):
    """Whether the recording has laser frames (the silhouettes and the carve then let a
    failed segmentation leave no hull, not an error: the laser's measurement goes on)."""
    return "laser" in recording_stages(RECORDINGS[wildcards.rec])


def get_calibration(wildcards):
    """The calibration file a scan uses instead of its own ({} when it keeps its own):
    re-calibrating re-runs the scans that use it, and only those."""
    calib = SCAN_CALIBRATION.get(wildcards.rec)
    return {"calibration": f"results/calibration/{calib}.yaml"} if calib else {}


def get_scan_inputs(wildcards):
    """A stage that reads the scan recording's cameras and transforms: the recording and
    the calibration it uses."""
    return {"recording": RECORDINGS[wildcards.rec].path, **get_calibration(wildcards)}


def get_silhouettes_inputs(wildcards):
    """The recording and its calibration, and with laser frames the triangulated clouds:
    their points on the object test the masks (a view that leaves many outside is
    segmented again from them). Not for a file that cannot be read: its silhouettes job
    runs and fails with the reader's message, beside its stripes job."""
    out = get_scan_inputs(wildcards)
    entry = RECORDINGS[wildcards.rec]
    if "laser" in recording_stages(entry) and getattr(entry.summary, "readable", True) \
            and config["segmentation"]["laser_reseed"]:
        out["clouds"] = f"results/{wildcards.rec}/clouds.npz"
    return out


def get_calibration_recording(wildcards):
    """The .mcap file of one calibration recording."""
    return CALIBRATIONS[wildcards.calib].path


def get_align_inputs(wildcards):
    """The sweep clouds, and the silhouettes with their recording when it has views (and
    the hull, whose box is the workspace of a recording without one)."""
    out = {"clouds": f"results/{wildcards.rec}/clouds.npz"}
    if "hull" in recording_stages(RECORDINGS[wildcards.rec]):
        out["silhouettes"] = f"results/{wildcards.rec}/silhouettes.npz"
        out["recording"] = RECORDINGS[wildcards.rec].path
        if not has_workspace_box(RECORDINGS[wildcards.rec]):
            out["hull"] = f"results/{wildcards.rec}/hull.npz"
    return out


def get_fuse_inputs(wildcards):
    """What fusion has: the hull (views), the aligned clouds (laser frames), or both."""
    stages = recording_stages(RECORDINGS[wildcards.rec])
    out = {}
    if "hull" in stages:
        out["hull"] = f"results/{wildcards.rec}/hull.npz"
    if "laser" in stages:
        out["aligned"] = f"results/{wildcards.rec}/aligned.npz"
    return out


def get_simplify_inputs(wildcards):
    """The fused mesh, and the hull (its voxel bounds the inferred surface's error)."""
    out = {"fused": f"results/{wildcards.rec}/fused.ply"}
    if "hull" in recording_stages(RECORDINGS[wildcards.rec]):
        out["hull"] = f"results/{wildcards.rec}/hull.npz"
    return out


def get_evaluate_inputs(wildcards):
    """The recording and every result it supports."""
    stages = recording_stages(RECORDINGS[wildcards.rec])
    out = {"recording": RECORDINGS[wildcards.rec].path, **get_calibration(wildcards),
           "mesh": f"results/{wildcards.rec}/mesh.ply",
           "fused": f"results/{wildcards.rec}/fused.ply",
           "measured": f"results/{wildcards.rec}/measured.ply"}
    if "hull" in stages:
        out["hull"] = f"results/{wildcards.rec}/hull.npz"
        out["silhouettes"] = f"results/{wildcards.rec}/silhouettes.npz"  # mask IoU
    if "laser" in stages:
        out["clouds"] = f"results/{wildcards.rec}/clouds.npz"
        out["aligned"] = f"results/{wildcards.rec}/aligned.npz"
    return out


def get_pictures_inputs(wildcards):
    """What the report's pictures of one recording draw: the recording (images), its
    metrics, the final mesh, and the stages' outputs it has data for."""
    stages = recording_stages(RECORDINGS[wildcards.rec])
    res = f"results/{wildcards.rec}"
    out = {"recording": RECORDINGS[wildcards.rec].path, **get_calibration(wildcards),
           "metrics": f"{res}/metrics.json", "mesh": f"{res}/mesh.ply"}
    if "hull" in stages:
        out["silhouettes"] = f"{res}/silhouettes.npz"
        out["hull_mesh"] = f"{res}/hull.ply"
    if "laser" in stages:
        out["stripes"] = f"{res}/stripes.npz"
        out["aligned"] = f"{res}/aligned.npz"
    return out


def get_foxglove_inputs(wildcards):
    """The clouds with the laser frames' stamps, the views' stamps, and the meshes of
    config foxglove.meshes that the recording has (no hull without views)."""
    stages = recording_stages(RECORDINGS[wildcards.rec])
    res = f"results/{wildcards.rec}"
    out = {}
    if "laser" in stages:
        out.update(stripes=f"{res}/stripes.npz", clouds=f"{res}/clouds.npz",
                   aligned=f"{res}/aligned.npz")
    if "hull" in stages:
        out["silhouettes"] = f"{res}/silhouettes.npz"
    for mesh in config["foxglove"]["meshes"]:
        if mesh != "hull" or "hull" in stages:
            out[mesh] = f"{res}/{mesh}.ply"
    return out


def recording_outputs(name):
    """The public outputs of one recording, as far as its data supports them."""
    stages = recording_stages(RECORDINGS[name])
    out = []
    if "hull" in stages:
        out.append(f"results/{name}/hull.ply")
    if "laser" in stages:
        out.append(f"results/{name}/aligned.ply")
    out += [f"results/{name}/fused.ply", f"results/{name}/measured.ply",
            f"results/{name}/mesh.ply", f"results/{name}/metrics.json"]
    if config["foxglove"]["enabled"]:
        out.append(f"results/{name}/results.mcap")
    return out


#: The jobs of a recording whose files the report shows (evaluate comes after every stage).
REPORT_JOBS = ("evaluate", "pictures", *(("foxglove",) if config["foxglove"]["enabled"] else ()))


def report_only():
    """Whether this is `snakemake --report FILE` (without --report-after-run): it runs no
    job, it gathers what a run made."""
    args = sys.argv[1:]
    return (any(a == "--report" or a.startswith("--report=") for a in args)
            and "--report-after-run" not in args)


def batch_recordings():
    """The recordings that the batch's outputs (rule all, the overview and tables) cover:
    every one; in `snakemake --report` after a run in which some failed, the finished
    ones (every output and picture written): the others are in the overview and
    batch.html with what failed, written by the run's onerror
    (robo3d.overview.write_unfinished_batch_report), since no job runs to make them."""
    if not report_only():
        return sorted(RECORDINGS)
    return finished_recordings(RECORDINGS, "results", REPORT_JOBS)


def get_all_outputs():
    """The public outputs of every recording, as far as its data supports them."""
    out = []
    for name in batch_recordings():
        out += recording_outputs(name)
    if RECORDINGS:
        out += ["results/batch.tsv", "results/overview.html"]
    for name in sorted(CALIBRATIONS):
        out += [f"results/calibration/{name}.yaml", f"results/calibration/{name}_report.json"]
    return out
