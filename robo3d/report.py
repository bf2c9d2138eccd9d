"""Pictures for the Snakemake report: what every stage of one recording made, drawn
headless and cheaply (OpenCV and Open3D ray casting; no display, no matplotlib).

- :func:`mask_overlay` / :func:`stripe_overlay`: a silhouette mask over its image, the
  stripe centres over their laser frame.
- :func:`masks_picture`, :func:`stripes_picture`: a grid of evenly spaced views / laser
  frames with those overlays.
- :func:`mesh_views`, :func:`points_views`: a mesh (ray cast) or a point cloud (z-buffered
  splats) from a few directions about the object's up axis (:func:`find_up`).
- :func:`timings_picture`: each stage's wall time and peak memory as bars.
- :func:`write_png`: writes a picture atomically.

Every picture is deterministic (the same inputs give the same bytes) and takes well
under a second or two at a few hundred pixels a tile: clouds are decimated for drawing
(evenly, by index), meshes are ray cast at the tile's size.

Up axis
-------
A recording's ``base`` frame need not have z up (a turntable photo set, a capture rig's
world frame with y up). :func:`find_up` takes it from the cameras. First from how they
were held: a camera held level (a person's, most robots') keeps its image rows
horizontal whatever it looks at, so up is perpendicular to every view's image rows; a
rig that turned its camera a quarter keeps the columns horizontal instead. When the
views' rows (or columns) lie in one plane (flatness, smallest over middle singular
value, under 0.25), up is that plane's normal, signed as the images' up (or toward the
cameras). Otherwise from where the cameras were: people and robots look at an object on
a table from above and around it, never from below the table, so the mean direction from
the object to the cameras points up; when that mean is short (a ring level with the
object) the ring's axis is up. The direction is snapped to the nearest axis of the frame
when within 25 degrees of it (rigs and robot bases are set up level). Without cameras,
+z (the convention of robot base frames, ROS REP 103).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .fusion import SOURCE_RGB, source_colors
from .viz import SWEEP_RGB

__all__ = ["find_up", "SWEEP_COLOURS", "SOURCE_COLOURS", "source_colours", "mask_overlay",
           "stripe_overlay",
           "to_rgb8", "tile_grid", "titled", "legend", "colour_bar", "placeholder",
           "masks_picture", "stripes_picture", "mesh_views", "points_views",
           "timings_picture", "write_png"]

log = logging.getLogger(__name__)

#: Colours of sweeps 0, 1, 2, ... (cycled), RGB 0-1: viz.SWEEP_RGB, as in rerun and results.mcap.
SWEEP_COLOURS = np.asarray(SWEEP_RGB, dtype=np.float64) / 255.0
#: Colours of a mesh vertex's ``source`` (0 measured by the laser, 1 inferred from the
#: visual hull, 2 filled), as in rerun: grey, orange, yellow.
SOURCE_COLOURS = {k: (tuple(float(c) / 255.0 for c in SOURCE_RGB[k]), label)
                  for k, label in enumerate(("measured by the laser",
                                             "inferred from the visual hull",
                                             "filled (gap closed)"))}
_FONT = 0  # cv2.FONT_HERSHEY_SIMPLEX
_SNAP_DEG = 25.0
_LEVEL_FLATNESS = 0.25


# ------------------------------------------------------------------------- up axis
def _level_axis(R: np.ndarray) -> tuple[np.ndarray, float, int] | None:
    """The direction perpendicular to one image axis of every camera, when there is one.

    A camera held level (no roll: a person's, most robots') has its image rows (camera x)
    horizontal, whatever it looks at; one turned a quarter has its columns (camera y)
    horizontal. The axis (x or y) whose directions over the views span a plane, and
    only a plane, gives up as that plane's normal. Returns (normal, flatness, axis) for
    the flatter of the two (flatness: smallest over middle singular value), or None
    when neither spans a plane (fewer than 3 views, or all turned alike)."""
    best = None
    for k in (0, 1):
        s, vt = np.linalg.svd(R[:, :, k], full_matrices=False)[1:]
        if s[1] < 0.2 * s[0]:  # the views' axes all alike: no plane
            continue
        flat = float(s[2] / s[1])
        if flat < _LEVEL_FLATNESS and (best is None or flat < best[1]):
            best = (vt[2], flat, k)
    return best


def find_up(object_centre: np.ndarray,
            camera_poses: Sequence[np.ndarray] = ()) -> tuple[np.ndarray, str]:
    """The object's up direction in its frame, found from the cameras (module notes).

    Parameters
    ----------
    object_centre : (3,) float64, metres
    camera_poses : sequence of (N, 4, 4) float64
        ``T_base_camera`` of the views of each camera (e.g. the silhouette views, the
        laser frames): each group is checked for a level image axis on its own.

    Returns
    -------
    up : (3,) float64
        Unit vector.
    how : str
        How it was found, for the pictures' captions.
    """
    c = np.asarray(object_centre, dtype=np.float64).reshape(3)
    groups = [np.asarray(T, dtype=np.float64).reshape(-1, 4, 4) for T in camera_poses]
    groups = [T[np.all(np.isfinite(T.reshape(len(T), -1)), axis=1)] for T in groups]
    groups = [T for T in groups if len(T) >= 3]
    if not groups:
        return np.array([0.0, 0.0, 1.0]), "+z (no cameras to tell)"
    cams = np.concatenate([T[:, :3, 3] for T in groups])
    d = cams - c
    d = d[np.linalg.norm(d, axis=1) > 0]
    mean = (d / np.linalg.norm(d, axis=1, keepdims=True)).mean(axis=0)
    level = [(r, T) for T in groups if (r := _level_axis(T[:, :3, :3])) is not None]
    if level:
        (up, _, k), T = min(level, key=lambda x: x[0][1])
        # toward the cameras (above the table); for level rows, toward the images' up
        side = -T[:, :3, 1].mean(axis=0) if k == 0 else mean
        up = up if up @ side >= 0 else -up
        how = f"normal to the cameras' level image {'rows' if k == 0 else 'columns'}"
    elif np.linalg.norm(mean) >= 0.25:
        up, how = mean / np.linalg.norm(mean), "the cameras' mean direction from the object"
    else:  # a ring level with the object: its axis, toward the cameras' side
        vt = np.linalg.svd(cams - cams.mean(axis=0), full_matrices=False)[2]
        up = vt[2] if vt[2] @ mean >= 0 else -vt[2]
        how = "the axis of the cameras' ring"
    k = int(np.argmax(np.abs(up)))
    if np.degrees(np.arccos(min(1.0, abs(up[k])))) <= _SNAP_DEG:
        up = np.sign(up[k]) * np.eye(3)[k]
        how += f", snapped to {'+-'[int(up[k] < 0)]}{'xyz'[k]}"
    return up / np.linalg.norm(up), how


def source_colours(source: np.ndarray) -> np.ndarray:
    """Colours (V, 3) in [0, 1] of mesh vertices by their ``source`` (:data:`SOURCE_COLOURS`;
    an unknown code takes the last one's)."""
    return source_colors(np.ravel(source)).astype(np.float64) / 255.0


# ------------------------------------------------------------------------- image helpers
def to_rgb8(image: np.ndarray) -> np.ndarray:
    """An image as (H, W, 3) uint8 RGB: grey is repeated, 16-bit scaled to its maximum."""
    img = np.asarray(image)
    if img.dtype != np.uint8:
        top = float(img.max()) if img.size else 1.0
        img = np.clip(img.astype(np.float64) * (255.0 / max(top, 1.0)), 0, 255).astype(np.uint8)
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be (H, W) or (H, W, 3), got {img.shape}")
    return img


def _resize(img: np.ndarray, width: int) -> np.ndarray:
    import cv2

    h, w = img.shape[:2]
    height = max(1, int(round(h * width / w)))
    return cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)


def mask_overlay(image: np.ndarray, mask: np.ndarray, width: int | None = None,
                 colour: tuple[int, int, int] = (0, 190, 255)) -> np.ndarray:
    """A silhouette over its image: the object tinted, its outline drawn, the background
    dimmed, so that a mask that misses or overflows the object shows at a glance.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 / uint16
    mask : (H, W) bool
    width : int, optional
        Width of the result in pixels (the outline stays 2 px wide); default the image's.
    colour : RGB uint8
        Tint and outline.

    Returns
    -------
    (h, width, 3) uint8 RGB
    """
    import cv2

    img = to_rgb8(image)
    m = np.asarray(mask, dtype=bool)
    if m.shape != img.shape[:2]:
        raise ValueError(f"mask must be {img.shape[:2]} bool, got {m.shape} {m.dtype}")
    if width is not None and width != img.shape[1]:
        img = _resize(img, width)
        m = cv2.resize(m.astype(np.uint8), img.shape[1::-1],
                       interpolation=cv2.INTER_NEAREST).astype(bool)
    out = img.astype(np.float32)
    tint = np.asarray(colour, dtype=np.float32)
    out[m] = 0.7 * out[m] + 0.3 * tint
    out[~m] *= 0.55
    out = out.round().astype(np.uint8)
    edge = cv2.morphologyEx(m.astype(np.uint8), cv2.MORPH_GRADIENT, np.ones((3, 3), np.uint8))
    out[edge > 0] = colour
    return out


def stripe_overlay(image: np.ndarray, u: np.ndarray, v: np.ndarray, width: int | None = None,
                   colour: tuple[int, int, int] = (0, 230, 90)) -> np.ndarray:
    """The stripe centres found in a laser frame, as dots over the frame.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8 / uint16
    u, v : (N,) float, pixels
        The centres (column, row) in the full-size image.
    width : int, optional
        Width of the result in pixels (default the image's).
    colour : RGB uint8

    Returns
    -------
    (h, width, 3) uint8 RGB
        The frame brightened (laser frames are dark), with a 2 x 2 dot per centre: where
        the dots leave the laser line uncovered the detector missed it.
    """
    img = to_rgb8(image)
    h0, w0 = img.shape[:2]
    if width is not None and width != w0:
        img = _resize(img, width)
    scale = img.shape[1] / w0
    gain = 200.0 / max(float(np.percentile(img, 99.9)), 1.0)
    out = np.clip(img.astype(np.float32) * min(gain, 4.0), 0, 255).astype(np.uint8)
    uu = np.asarray(u, dtype=np.float64).ravel() * scale
    vv = np.asarray(v, dtype=np.float64).ravel() * scale
    if uu.shape != vv.shape:
        raise ValueError(f"u and v must have the same length, got {uu.shape} and {vv.shape}")
    x = np.floor(uu).astype(np.int64)
    y = np.floor(vv).astype(np.int64)
    ox, oy = np.meshgrid([0, 1], [0, 1])
    xs = (x[:, None] + ox.ravel()).ravel()
    ys = (y[:, None] + oy.ravel()).ravel()
    ok = (xs >= 0) & (xs < out.shape[1]) & (ys >= 0) & (ys < out.shape[0])
    out[ys[ok], xs[ok]] = colour
    return out


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.45,
          colour: tuple[int, int, int] = (0, 0, 0), thick: int = 1) -> None:
    import cv2

    cv2.putText(img, text, org, _FONT, scale, colour, thick, cv2.LINE_AA)


def _text_width(text: str, scale: float = 0.45) -> int:
    import cv2

    return int(cv2.getTextSize(text, _FONT, scale, 1)[0][0])


def tile_grid(tiles: Sequence[np.ndarray], captions: Sequence[str], cols: int,
              pad: int = 6) -> np.ndarray:
    """Tiles (RGB uint8, any heights, equal widths) in a grid with a caption under each."""
    if not tiles:
        raise ValueError("tile_grid needs at least one tile")
    w = max(t.shape[1] for t in tiles)
    cap = 20
    cell_h = max(t.shape[0] for t in tiles) + cap
    rows = -(-len(tiles) // cols)
    out = np.full((rows * (cell_h + pad) + pad, cols * (w + pad) + pad, 3), 255, np.uint8)
    for k, (t, c) in enumerate(zip(tiles, captions, strict=True)):
        y0 = pad + (k // cols) * (cell_h + pad)
        x0 = pad + (k % cols) * (w + pad)
        out[y0:y0 + t.shape[0], x0:x0 + t.shape[1]] = t
        _text(out, c, (x0 + 2, y0 + t.shape[0] + 15), 0.42)
    return out


def titled(img: np.ndarray, title: str, lines: Sequence[str] = ()) -> np.ndarray:
    """The picture under a title line and a few smaller lines of explanation."""
    width = max(img.shape[1], 10 + _text_width(title, 0.6),
                *(10 + _text_width(s, 0.45) for s in lines))
    head = np.full((30 + 18 * len(lines), width, 3), 255, np.uint8)
    _text(head, title, (8, 21), 0.6)
    for i, s in enumerate(lines):
        _text(head, s, (8, 42 + 18 * i), 0.45, (60, 60, 60))
    body = np.full((img.shape[0], width, 3), 255, np.uint8)
    body[:, : img.shape[1]] = img
    return np.concatenate([head, body], axis=0)


def legend(items: Sequence[tuple[Sequence[float], str]], width: int) -> np.ndarray:
    """Coloured swatches with their labels (colours RGB in [0, 1]), in as many rows of
    ``width`` pixels as they need."""
    rows: list[list[tuple[int, Sequence[float], str]]] = [[]]
    x = 10
    for colour, label in items:
        w = 34 + _text_width(label)
        if rows[-1] and x + w - 15 > width:
            rows.append([])
            x = 10
        rows[-1].append((x, colour, label))
        x += w
    out = np.full((28 * len(rows), width, 3), 255, np.uint8)
    for r, row in enumerate(rows):
        for x0, colour, label in row:
            y = 28 * r
            out[y + 8:y + 22, x0:x0 + 14] = (np.asarray(colour) * 255).round().astype(np.uint8)
            _text(out, label, (x0 + 19, y + 20))
    return out


def colour_bar(vmax: float, label: str, width: int) -> np.ndarray:
    """The error colour ramp of :func:`robo3d.render.colormap` from 0 to ``vmax``."""
    from .render import colormap

    out = np.full((32, width, 3), 255, np.uint8)
    n = max(40, width // 3)
    x0 = 60
    out[8:22, x0:x0 + n] = (colormap(np.linspace(0, vmax, n), vmax)[None] * 255).astype(np.uint8)
    _text(out, "0", (x0 - 16, 20))
    _text(out, f">= {vmax:g} {label}", (x0 + n + 8, 20))
    return out


def placeholder(text: str, width: int = 480) -> np.ndarray:
    """A small picture that says why there is no picture."""
    out = np.full((60, max(width, 20 + _text_width(text, 0.5)), 3), 245, np.uint8)
    _text(out, text, (10, 36), 0.5, (90, 90, 90))
    return out


def write_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an RGB uint8 picture as PNG, atomically."""
    import cv2

    from .atomic import atomic_path

    ok, buf = cv2.imencode(".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
    return path


# ------------------------------------------------------------------------- stage pictures
def _by_stamp(messages: Sequence[Any], stamps_ns: np.ndarray) -> list[Any | None]:
    """The message of each stamp (None where no message has it)."""
    known = {int(m.timestamp_ns): m for m in messages}
    return [known.get(int(t)) for t in np.asarray(stamps_ns).ravel()]


def masks_picture(rec: Any, sil: Any, *, n: int = 8, tile_px: int = 240,
                  mask_iou: Mapping[int, float] | None = None,
                  left_out: set[int] | frozenset[int] = frozenset(),
                  from_laser: set[int] | frozenset[int] = frozenset(),
                  notes: Sequence[str] = ()) -> np.ndarray:
    """Evenly spaced silhouette views with their masks over their images.

    Parameters
    ----------
    rec : robo3d.recording.model.Recording
        The recording, read with its views (images decoded here).
    sil : robo3d.artefacts.Silhouettes
    n : int
        Views shown at most.
    tile_px : int
        Width of each view, pixels.
    mask_iou : mapping view -> IoU, optional
        Each view's mask against the true one (ground truth), for the captions.
    left_out : set of int
        Views the carve left out (its agreement check), said in the captions.
    from_laser : set of int
        Views segmented again from the laser's points (the colour model's mask left many
        of them outside), said in the captions.
    notes : sequence of str
        More lines under the title (what the laser said of the masks).
    """
    from .viz import spaced_indices

    masks = sil.view_masks()
    msgs = _by_stamp(sorted(rec.views, key=lambda m: m.timestamp_ns), sil.stamps_ns)
    tiles, caps = [], []
    for i in spaced_indices(len(masks), n):
        if msgs[i] is None:
            continue
        tiles.append(mask_overlay(rec.decode(msgs[i]), masks[i], tile_px))
        cap = f"view {i}"
        if mask_iou and i in mask_iou:
            cap += f", IoU {mask_iou[i]:.3f}"
        if i in from_laser:
            cap += ", from the laser"
        if i in left_out:
            cap += ", left out of the hull"
        caps.append(cap)
    if not tiles:
        return placeholder("the recording's views do not match silhouettes.npz")
    n_flag = 0 if sil.qa_flagged is None else int(np.sum(sil.qa_flagged))
    return titled(tile_grid(tiles, caps, cols=min(4, len(tiles))),
                  f"Silhouettes: {len(tiles)} of {len(masks)} views, mask outlined",
                  [f"object tinted, background dimmed; {n_flag} view(s) flagged by the "
                   f"mask check, {len(left_out)} left out of the hull"
                   + (f", {len(from_laser)} segmented again from where the laser measured "
                      "the object" if from_laser else ""), *notes])


def stripes_picture(rec: Any, stripes: Any, *, n: int = 6, tile_px: int = 320) -> np.ndarray:
    """Evenly spaced laser frames (among those where a stripe was found) with their
    stripe centres drawn over them."""
    from .viz import spaced_indices

    counts = stripes.counts
    with_stripe = np.nonzero(counts > 0)[0]
    msgs = _by_stamp(sorted(rec.laser_frames, key=lambda m: m.timestamp_ns), stripes.stamps_ns)
    tiles, caps = [], []
    t0 = int(stripes.stamps_ns[0]) if len(stripes.stamps_ns) else 0
    for i in with_stripe[spaced_indices(len(with_stripe), n)]:
        if msgs[i] is None:
            continue
        a, b = stripes.offsets[i], stripes.offsets[i + 1]
        tiles.append(stripe_overlay(rec.decode(msgs[i]), stripes.u[a:b], stripes.v[a:b],
                                    tile_px))
        caps.append(f"frame {i}, t = {(int(stripes.stamps_ns[i]) - t0) * 1e-9:.1f} s, "
                    f"{b - a} centres")
    if not tiles:
        return placeholder(f"no stripe found in any of the {len(counts)} laser frames")
    return titled(tile_grid(tiles, caps, cols=min(3, len(tiles))),
                  f"Laser stripes: {len(tiles)} of {len(counts)} frames, centres in green",
                  [f"a stripe was found in {len(with_stripe)} of {len(counts)} frames, "
                   f"{len(stripes.u)} centres in all; frames brightened for display"])


def mesh_views(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None,
               up: np.ndarray, *, tile_px: int = 300,
               views: Sequence[tuple[float, float]] = ((30, 30), (150, 30), (270, 30),
                                                       (0, 88))) -> list[np.ndarray]:
    """A mesh ray cast from several (azimuth, elevation) directions about ``up``."""
    from .render import render_mesh_views

    return render_mesh_views(vertices, faces, views, vertex_colors=colours, width=tile_px,
                             height=int(round(tile_px * 0.75)), up=up)


def points_views(points: np.ndarray, colours: np.ndarray, up: np.ndarray, *,
                 normals: np.ndarray | None = None, tile_px: int = 300,
                 max_points: int = 60000,
                 views: Sequence[tuple[float, float]] = ((30, 30), (150, 30), (270, 30),
                                                         (0, 88))) -> list[np.ndarray]:
    """A point cloud from several directions (decimated evenly to ``max_points``)."""
    from .render import render_points

    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    keep = np.unique(np.linspace(0, len(p) - 1, min(len(p), max_points)).round().astype(int))
    if not len(p):
        keep = keep[:0]
    nrm = None if normals is None else np.asarray(normals)[keep]
    h = int(round(tile_px * 0.75))
    return [render_points(p[keep], np.asarray(colours)[keep], normals=nrm, azimuth_deg=a,
                          elevation_deg=e, width=tile_px, height=h, up=up) for a, e in views]


def timings_picture(timings: Mapping[str, Any], width: int = 720) -> np.ndarray:
    """Each stage's wall time (s) and peak resident memory (MB) as horizontal bars."""
    rows = [(k, v) for k, v in timings.items()
            if isinstance(v, Mapping) and isinstance(v.get("seconds"), int | float)]
    if not rows:
        return placeholder("no stage timings in metrics.json")
    label_w, bar_w, row_h = 110, (width - 110 - 20) // 2 - 70, 22
    out = np.full((30 + row_h * len(rows) + 10, width, 3), 255, np.uint8)
    secs = np.array([float(v["seconds"]) for _, v in rows])
    mems = np.array([float(v["max_rss_mb"]) if isinstance(v.get("max_rss_mb"), int | float)
                     else np.nan for _, v in rows])
    x_mem = label_w + bar_w + 80
    _text(out, "wall time, s", (label_w, 18))
    _text(out, "peak memory (resident), MB", (x_mem, 18))
    s_max = max(float(secs.max()), 1e-9)
    m_max = max(float(np.nanmax(mems)) if np.isfinite(mems).any() else 1.0, 1e-9)
    for k, ((name, _), s, m) in enumerate(zip(rows, secs, mems, strict=True)):
        y = 30 + k * row_h
        _text(out, name, (8, y + 15))
        out[y + 4:y + row_h - 4, label_w:label_w + max(1, int(bar_w * s / s_max))] = (70, 130, 180)
        _text(out, f"{s:.1f}", (label_w + int(bar_w * s / s_max) + 5, y + 15))
        if np.isfinite(m):
            out[y + 4:y + row_h - 4, x_mem:x_mem + max(1, int(bar_w * m / m_max))] = (180, 120, 60)
            _text(out, f"{m:.0f}", (x_mem + int(bar_w * m / m_max) + 5, y + 15))
        else:
            _text(out, "not measured", (x_mem, y + 15), 0.42, (120, 120, 120))
    total = timings.get("total_seconds")
    return titled(out, "Stage timings and memory",
                  [f"total {total:.1f} s of job time" if isinstance(total, int | float)
                   else "total not known",
                   "from Snakemake's benchmark files (one job per stage)"])
