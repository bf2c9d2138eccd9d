"""The ``robo3d`` command line.

Each subcommand is a pair of functions registered in :data:`COMMANDS`: one that adds
its arguments to an ``argparse`` subparser, one that runs it and returns the exit
status. To add a command (``robo3d info``, ...), write the pair and append it.

``robo3d simulate OBJECT OUT.mcap [options]``
    Simulate a scan recording (see :mod:`robo3d.simulate`).
``robo3d simulate --demo DIR [--missing]``
    Regenerate the demo recordings into ``DIR``, deterministically (``--missing``: only
    those not there yet; ``./run.sh demo`` does this first).
``robo3d simulate-calibration OUT.mcap [--rig robot|fixed] [--seed N] [--small] [options]``
    Simulate a calibration recording of the scan cell with its truth (see
    :mod:`robo3d.sim.calibration`).
``robo3d info RECORDING [--config CONFIG] [--topic ROLE=NAME] [--frame ROLE=NAME] [--json]``
    What a recording holds and whether each stage can use it (see :mod:`robo3d.info`);
    exit status 1 when it is not fit, with the reasons.
``robo3d status [--results DIR] [--logs DIR] [--json]``
    After a batch: per recording, the stages done, failed (with the first error line of
    their log) and not run; exit status 1 when a recording failed.
``robo3d view REC [--results DIR] [--web] [--bind ADDR] [--web-port N] [--grpc-port N]``
    Every stage's rerun log of a recording together, with a designed layout (see
    :mod:`robo3d.view`); ``--web`` serves the web viewer and prints its address.
``robo3d warm-up [--processes N]``
    Compile the numba kernels into the cache once, before many jobs start side by side
    (see :mod:`robo3d.warmup`).
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from . import __version__
from .errors import Robo3dError

__all__ = ["main", "build_parser", "Command", "COMMANDS"]

_log = logging.getLogger("robo3d")


@dataclass(frozen=True)
class Command:
    """A subcommand: its name, one-line help, argument builder and runner."""

    name: str
    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


# --------------------------------------------------------------------------- simulate
def _add_simulate(p: argparse.ArgumentParser) -> None:
    from .simulate import OBJECT_NAMES, SimulationParams

    d = SimulationParams()
    p.add_argument("object", nargs="?", metavar="OBJECT",
                   help=f"object to scan: {', '.join(OBJECT_NAMES)} (omit with --object-mesh)")
    p.add_argument("out", nargs="?", help="output .mcap file")
    p.add_argument("--demo", metavar="DIR",
                   help="regenerate the demo recordings into DIR (other options ignored)")
    p.add_argument("--missing", action="store_true",
                   help="with --demo: only the demo recordings not yet in DIR")
    p.add_argument("--no-views", action="store_true", help="laser sweeps only")
    p.add_argument("--no-laser", action="store_true", help="views only (a photo set)")
    p.add_argument("--laser-off", action="store_true",
                   help="also a laser-off frame at each laser frame's pose, on "
                        "/camera/laser_off (for stripes.laser_off_topic)")
    p.add_argument("--encoding", choices=("protobuf", "json"), default="protobuf",
                   help="message encoding (default %(default)s)")
    p.add_argument("--threads", type=int, default=1,
                   help="ray-casting threads, 0 for all cores (default %(default)s)")
    r = p.add_argument_group("scene (issue 10: what real cells record)")
    r.add_argument("--scene", choices=("demo", "cell"), default="demo",
                   help="demo: the demo cell (dark table, dimmed laser frames, red laser, "
                        "grey object); cell: room light in the laser frames, a coloured "
                        "laser, a coloured textured glossy object on a bright marker table "
                        "before a wall, JPEG 80, a webcam's noise (default %(default)s)")
    r.add_argument("--preset", choices=("full", "small"), default="full",
                   help="small: 320x240, 10 views, 3 sweeps of 40 frames (default "
                        "%(default)s)")
    r.add_argument("--laser", choices=("red", "green", "blue"), default=None,
                   help="laser colour (cell scene; default red)")
    r.add_argument("--object-color", nargs="+", metavar="NAME_OR_RGB", default=None,
                   help="object colour: a name (grey, white, orange, red, green, blue, "
                        "yellow, brown, black) or three albedos R G B (cell scene; default "
                        "orange)")
    r.add_argument("--object-texture", choices=("none", "blotches", "checker", "stripes"),
                   default=None, help="procedural texture (cell scene; default blotches)")
    r.add_argument("--table-markers", choices=("none", "aruco", "checker", "dots"),
                   default=None, help="printed pattern on the table (cell scene; default "
                                      "aruco)")
    r.add_argument("--no-wall", action="store_true", help="cell scene without the wall")
    r.add_argument("--no-box", action="store_true",
                   help="no workspace box in the recording's metadata (a ROS bag has none)")
    r.add_argument("--turntable", action="store_true",
                   help="a turntable rig: camera and laser fixed in the room (the sheet "
                        "upright, at --sweep-elevation), the object and its plate turning "
                        "under them, the wall and the light staying in the room; each sweep "
                        "one revolution")
    r.add_argument("--object-mesh", metavar="FILE", default=None,
                   help="a mesh file (STL, PLY, OBJ) as the object, placed standing on the "
                        "table at the workspace centre")
    r.add_argument("--mesh-unit", choices=("m", "cm", "mm", "um", "in"), default=None,
                   help="unit of --object-mesh's coordinates (default m)")
    r.add_argument("--view-supersample", type=int, default=None, metavar="N",
                   help="rays per pixel side on the views' geometric edges, as a camera "
                        "integrates the pixel (1: the pixel centre's ray only, a staircase "
                        "outline, the renderer before 2026-12-03; default 4)")
    # every option below defaults to SimulationParams' value (shown), so that a bare
    # command line gives exactly the library's defaults
    g = p.add_argument_group("simulation parameters")
    for flag, field, kind, unit, text in _SIM_OPTIONS:
        default = getattr(d, field)
        shown = default if not isinstance(default, tuple) else " ".join(map(str, default))
        kw: dict = {"dest": field, "default": None, "metavar": unit or None,
                    "help": f"{text} (default {shown})"}
        if kind == "range":
            kw.update(type=float, nargs=2, metavar=("LO", "HI"),
                      help=f"{text}, {unit}: magnitude uniform in [LO, HI] "
                           f"(default {shown})")
        elif kind == "floats":
            kw.update(type=float, nargs="+")
        elif isinstance(kind, tuple):
            kw.update(choices=kind)
            kw.pop("metavar")
        else:
            kw["type"] = kind
        g.add_argument(flag, **kw)


#: (flag, SimulationParams field, type / choices / "range" / "floats", unit)
_SIM_OPTIONS: list[tuple[str, str, object, str, str]] = [
    ("--seed", "seed", int, "N",
     "random seed"),
    ("--views", "views", int, "N",
     "silhouette views"),
    ("--sweeps", "sweeps", int, "N",
     "laser sweeps (the last from above)"),
    ("--width", "width", int, "PX",
     "image width"),
    ("--height", "height", int, "PX",
     "image height"),
    ("--view-elevations", "view_elevations_deg", "floats", "DEG",
     "one ring of views per elevation"),
    ("--view-distance", "view_distance", float, "M",
     "camera-to-object distance of the views"),
    ("--sweep-elevation", "sweep_elevation_deg", float, "DEG",
     "elevation of the upper ring of side sweeps"),
    ("--sweep-spacing", "sweep_spacing", float, "M",
     "camera travel per laser frame"),
    ("--sweep-frames", "sweep_frames", int, "N",
     "frames per sweep (overrides --sweep-spacing)"),
    ("--sweep-speed", "sweep_speed", float, "M_PER_S",
     "camera speed during a sweep"),
    ("--sweep-gap", "sweep_gap_s", float, "S",
     "pause between sweeps"),
    ("--tf-rate", "tf_rate_hz", float, "HZ",
     "/tf rate while sweeping"),
    ("--view-encoding", "view_encoding", ("jpeg", "png", "rgb8", "bgr8"), "",
     "encoding of the views"),
    ("--laser-encoding", "laser_encoding", ("png", "mono8", "jpeg"), "",
     "encoding of the laser frames (mono8 with a coloured laser: a monochrome camera)"),
    ("--jpeg-quality", "jpeg_quality", int, "Q",
     "JPEG quality"),
    ("--view-noise", "view_read_noise_dn", float, "DN",
     "read noise of the views"),
    ("--laser-noise", "laser_read_noise_dn", float, "DN",
     "read noise of the laser frames"),
    ("--gain", "gain_dn_per_electron", float, "DN_PER_E",
     "shot noise: DN per electron (0: none)"),
    ("--sweep-error-mm", "sweep_error_mm", "range", "mm",
     "robot translation error per sweep"),
    ("--sweep-error-deg", "sweep_error_deg", "range", "degrees",
     "robot rotation error per sweep"),
    ("--view-error-mm", "view_error_mm", "range", "mm",
     "robot translation error per view"),
    ("--view-error-deg", "view_error_deg", "range", "degrees",
     "robot rotation error per view"),
    ("--mesh-faces", "mesh_faces", int, "N",
     "triangles of the truth mesh"),
    ("--robot-error", "robot_error", ("constant", "drift"), "",
     "robot error model: constant per sweep, or drifting within a sweep plus a "
     "pose-dependent term"),
    ("--drift-mm", "drift_mm", "range", "mm",
     "drift model: translation drift within a sweep"),
    ("--drift-deg", "drift_deg", "range", "degrees",
     "drift model: rotation drift within a sweep"),
    ("--pose-error-mm-per-m", "pose_error_mm_per_m", float, "MM_PER_M",
     "drift model: pose-dependent translation error gradient"),
    ("--pose-error-deg-per-m", "pose_error_deg_per_m", float, "DEG_PER_M",
     "drift model: pose-dependent rotation error gradient"),
    ("--clock-lag-ms", "clock_lag_ms", float, "MS",
     "the camera clock is late: each image is stamped this much before it was taken"),
    ("--rolling-shutter-ms", "rolling_shutter_ms", float, "MS",
     "a rolling shutter: a laser frame's last row is exposed this much after its first "
     "(the robot moving meanwhile); 0: a global shutter"),
    ("--vignetting", "vignetting", float, "FRACTION",
     "light lost in the image corners"),
    ("--laser-speckle", "laser_speckle", float, "CONTRAST",
     "laser speckle: the stripe's light times a random factor of mean 1 and this standard "
     "deviation (0: none, 1: fully developed), a new pattern in every frame"),
    ("--speckle-grain", "speckle_grain_px", float, "PX",
     "size of a speckle grain in pixels"),
]


def _run_simulate(args: argparse.Namespace) -> int:
    from .simulate import simulate_recording, write_demos

    if args.demo:  # each recording is logged by the library as it is written
        write_demos(args.demo, threads=args.threads, missing_only=args.missing)
        return 0
    from .simulate import OBJECT_NAMES, SimulationParams

    obj, out = args.object, args.out
    if args.object_mesh and out is None:  # "simulate --object-mesh part.stl OUT.mcap"
        obj, out = None, obj
    if not out or (obj is None and not args.object_mesh):
        raise Robo3dError("simulate needs OBJECT and OUT.mcap, or --object-mesh FILE and "
                          "OUT.mcap (or --demo DIR)")
    if obj is not None and obj not in OBJECT_NAMES:
        raise Robo3dError(f"unknown object {obj!r}; expected one of {', '.join(OBJECT_NAMES)} "
                          "(or --object-mesh FILE)")
    overrides = {field: getattr(args, field) for _, field, _, _, _ in _SIM_OPTIONS
                 if getattr(args, field) is not None}
    if args.no_views:
        overrides["views"] = 0
    if args.no_laser:
        overrides["sweeps"] = 0
    if args.laser_off:
        overrides["laser_off"] = True
    if args.turntable:
        overrides["turntable"] = True
    if args.no_box:
        overrides["workspace_box"] = False
    if args.object_mesh:
        overrides["object_mesh"] = args.object_mesh
    if args.mesh_unit:
        overrides["mesh_unit"] = args.mesh_unit
    cell_opts = {k: v for k, v in (("laser", args.laser),
                                   ("texture", args.object_texture),
                                   ("markers", args.table_markers)) if v is not None}
    if args.object_color is not None:
        c = args.object_color
        try:
            cell_opts["object_color"] = c[0] if len(c) == 1 else tuple(float(x) for x in c)
        except ValueError:
            raise Robo3dError(f"--object-color takes a name or three numbers, got {c}") from None
        if len(c) not in (1, 3):
            raise Robo3dError(f"--object-color takes a name or three numbers, got {c}")
    if args.scene == "cell":
        params = SimulationParams.cell(small=args.preset == "small", wall=not args.no_wall,
                                       **cell_opts)
    else:
        if cell_opts or args.no_wall:
            raise Robo3dError("--laser, --object-color, --object-texture, --table-markers "
                              "and --no-wall need --scene cell")
        params = (SimulationParams.small() if args.preset == "small"
                  else SimulationParams())
    try:
        if args.view_supersample is not None:
            params = dataclasses.replace(params, appearance=dataclasses.replace(
                params.appearance, view_supersample=args.view_supersample))
        simulate_recording(out, obj, params=params, threads=args.threads,
                           message_encoding=args.encoding, **overrides)
    except ValueError as exc:  # a parameter out of range, an unknown colour
        raise Robo3dError(str(exc)) from None
    return 0


# --------------------------------------------------------------------------- simulate-calibration
def _add_simulate_calibration(p: argparse.ArgumentParser) -> None:
    from .sim.calibration import DEFECTS, CalibrationOptions

    d = CalibrationOptions()
    p.add_argument("out", help="output .mcap file")
    p.add_argument("--rig", choices=("robot", "fixed"), default="robot",
                   help="robot: the robot moves the camera over a static board; fixed: a "
                        "fixed camera (base) and a hand-held board (default %(default)s)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed of the session (default: the cell's, 0)")
    p.add_argument("--scene", choices=("demo", "cell"), default="cell",
                   help="the scan cell to calibrate (as robo3d simulate --scene; default "
                        "%(default)s)")
    p.add_argument("--small", action="store_true",
                   help="320x240, 8 views and 4 laser frames (tests)")
    p.add_argument("--width", type=int, default=None, help="image width, px (default 640)")
    p.add_argument("--height", type=int, default=None, help="image height, px (default 480)")
    p.add_argument("--views", type=int, default=None,
                   help=f"board views, bad ones included (default {d.views})")
    p.add_argument("--laser-frames", type=int, default=None,
                   help=f"laser frames, each with a companion view (default {d.laser_frames})")
    p.add_argument("--defects", nargs="*", choices=DEFECTS, default=None,
                   help=f"one bad view of each kind given, none without a value (default "
                        f"{' '.join(d.defects)})")
    p.add_argument("--encoding", choices=("protobuf", "json"), default="protobuf",
                   help="message encoding (default %(default)s)")
    p.add_argument("--threads", type=int, default=1,
                   help="ray-casting threads, 0 for all cores (default %(default)s)")


def _run_simulate_calibration(args: argparse.Namespace) -> int:
    from .simulate import SimulationParams, simulate_calibration

    size = {k: v for k, v in (("width", args.width), ("height", args.height)) if v is not None}
    if args.scene == "cell":
        params = SimulationParams.cell(small=args.small, **size)
    else:
        params = (SimulationParams.small(**size) if args.small else SimulationParams(**size))
    options = {k: v for k, v in (("views", args.views), ("laser_frames", args.laser_frames),
                                 ("defects", args.defects)) if v is not None}
    try:
        simulate_calibration(args.out, rig=args.rig, seed=args.seed, params=params,
                             small=args.small, threads=args.threads,
                             message_encoding=args.encoding, **options)
    except ValueError as exc:  # an option out of range
        raise Robo3dError(str(exc)) from None
    return 0


# --------------------------------------------------------------------------- info
def _pairs(items: list[str] | None, what: str, allowed: tuple[str, ...]) -> dict[str, str]:
    out = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or key not in allowed or not value:
            raise ValueError(f"--{what} must be ROLE=NAME with ROLE among "
                             f"{', '.join(allowed)}, got {item!r}")
        out[key] = value
    return out


def _add_info(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", help="an .mcap file or a rosbag2 directory")
    p.add_argument("--config", metavar="YAML",
                   help="pipeline config whose topics, frames and timing apply "
                        "(default: the shipped config/config.yaml)")
    p.add_argument("--topic", action="append", metavar="ROLE=NAME",
                   help="map a topic role, e.g. --topic views=/camera/color/image_raw "
                        "(repeatable; overrides the config)")
    p.add_argument("--frame", action="append", metavar="ROLE=NAME",
                   help="map a frame role, e.g. --frame base=base_link (repeatable)")
    p.add_argument("--json", action="store_true", help="print the analysis as JSON")


def _run_info(args: argparse.Namespace) -> int:
    from .atomic import dumps_json
    from .config import load_config
    from .info import format_info, inspect_with_config
    from .recording.model import FRAME_ROLES

    cfg = load_config(args.config) if args.config else load_config()
    cfg["topics"].update(_pairs(args.topic, "topic", ("tf", "tf_static", "calibration",
                                                      "views", "laser", "joint_states")))
    cfg["frames"].update(_pairs(args.frame, "frame", FRAME_ROLES))
    info = inspect_with_config(args.recording, cfg)
    sys.stdout.write((dumps_json(info) if args.json else format_info(info)) + "\n")
    return 0 if info["fit"] else 1


# --------------------------------------------------------------------------- status
def _add_status(p: argparse.ArgumentParser) -> None:
    p.add_argument("--results", default="results", help="results folder (default %(default)s)")
    p.add_argument("--logs", default="logs", help="logs folder (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print the status as JSON")


def _run_status(args: argparse.Namespace) -> int:
    from .atomic import dumps_json
    from .info import batch_status, format_batch_status

    status = batch_status(args.results, args.logs)
    if not status["recordings"] and not status["calibrations"]:
        _log.error("no results: neither %s nor %s holds a recording's results (run the "
                   "workflow first, or point --results/--logs at its folders)",
                   args.results, args.logs)
        return 1
    sys.stdout.write((dumps_json(status) if args.json else format_batch_status(status)) + "\n")
    failed_calibrations = [n for n, c in status["calibrations"].items() if c["status"] == "failed"]
    return 1 if status["failed"] or failed_calibrations else 0


# --------------------------------------------------------------------------- view
def _add_view(p: argparse.ArgumentParser) -> None:
    p.add_argument("recording", metavar="REC",
                   help="a recording's name (its logs in RESULTS/REC/) or a folder of .rrd files")
    p.add_argument("--results", default="results", help="results folder (default %(default)s)")
    p.add_argument("--web", action="store_true",
                   help="serve the web viewer (no display needed) and print its address")
    p.add_argument("--bind", default="127.0.0.1", metavar="ADDR",
                   help="address the viewer's servers listen on (default %(default)s: this "
                        "machine only; 0.0.0.0 opens them to the network)")
    p.add_argument("--web-port", type=int, default=9090, metavar="N",
                   help="HTTP port of the web viewer (default %(default)s; 0: a free one)")
    p.add_argument("--grpc-port", type=int, default=9876, metavar="N",
                   help="port of rerun's gRPC server (default %(default)s; 0: a free one)")
    p.add_argument("--analytics", action="store_true",
                   help="let rerun send its anonymous usage data as its own settings say "
                        "(off by default)")
    p.add_argument("--save-blueprint", metavar="PATH",
                   help="only write the layout as a rerun blueprint (.rbl) to PATH and exit "
                        "(open it with: rerun REC/*.rrd PATH)")


def _run_view(args: argparse.Namespace) -> int:
    from pathlib import Path

    from .view import logged_entities, save_blueprint, stage_logs, view_recording

    folder = Path(args.recording)
    if not (folder.is_dir() and any(folder.glob("*.rrd"))):
        folder = Path(args.results) / args.recording
    if args.save_blueprint:
        out = save_blueprint(args.save_blueprint, logged_entities(stage_logs(folder)))
        _log.info("wrote %s", out)
        return 0
    return view_recording(folder, web=args.web, bind=args.bind, web_port=args.web_port,
                          grpc_port=args.grpc_port, analytics=args.analytics)


# ---------------------------------------------------------------------------- warm-up
def _add_warm_up(p: argparse.ArgumentParser) -> None:
    p.add_argument("--processes", type=int, default=2,
                   help="compile the detector, the carver and the geometry side by side in "
                        "this many processes (default 2; 1: one after the other)")
    p.add_argument("--all-types", action="store_true",
                   help="also the detector on 16-bit and float frames and with its other "
                        "methods (band, gaussian): the test suite's stripe tests use them")


def _run_warm_up(args: argparse.Namespace) -> int:
    from .warmup import compile_kernels

    _log.info("compiling the numba kernels, or loading them from the cache (tens of seconds "
              "the first time after an install, about a second after)")
    t = compile_kernels(args.processes, all_types=args.all_types)
    other = (f", 16-bit and float frames {t['stripes_deep']:.1f} s, other methods "
             f"{t['stripes_methods']:.1f} s" if "stripes_deep" in t else "")
    _log.info("kernels compiled or loaded from the cache in %.1f s (stripe detector %.1f s%s, "
              "carver %.1f s, geometry %.1f s)", t["total"], t["stripes"], other, t["carver"],
              t["geometry"])
    return 0


#: The registered subcommands, in the order ``robo3d --help`` lists them.
COMMANDS: list[Command] = [
    Command("simulate", "simulate a scan recording with ground truth (or the demos)",
            _add_simulate, _run_simulate),
    Command("simulate-calibration", "simulate a calibration recording (a checkerboard, "
            "robot cell or fixed rig) with its truth", _add_simulate_calibration,
            _run_simulate_calibration),
    Command("info", "what a recording holds and whether the pipeline can use it",
            _add_info, _run_info),
    Command("status", "what a batch run made, and why its failed jobs failed",
            _add_status, _run_status),
    Command("view", "open a recording's rerun logs together with a designed layout "
            "(--web: in a browser)", _add_view, _run_view),
    Command("warm-up", "compile the numba kernels into the cache once (a fresh install), "
            "before many jobs start side by side", _add_warm_up, _run_warm_up),
]


def build_parser() -> argparse.ArgumentParser:
    """The ``robo3d`` argument parser with every registered subcommand."""
    parser = argparse.ArgumentParser(
        prog="robo3d", description="Measured 3D models from a robot-carried camera and "
                                   "line laser.")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    parser.add_argument("--version", action="version",
                        version=f"robo3d {__version__} (python {sys.version.split()[0]})")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for cmd in COMMANDS:
        p = sub.add_parser(cmd.name, help=cmd.help, description=cmd.help)
        cmd.add_arguments(p)
        p.set_defaults(_run=cmd.run)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``robo3d`` console script; returns the exit status.

    Errors robo3d raises on purpose (:class:`~robo3d.errors.Robo3dError`, bad
    parameters) are reported in one line with status 1; anything else is a bug and
    keeps its traceback.
    """
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO,
                        format="%(levelname)s %(name)s: %(message)s", stream=sys.stderr)
    try:
        return int(args._run(args))
    except (Robo3dError, ValueError, FileNotFoundError) as exc:
        _log.error("%s", exc)
        return 1


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
