"""Laser stripe detection: one sub-pixel stripe centre per image column (or row).

Implements the seed's §4.2 ("Detection of the laser path") and finishes its last step,
"associate a line to the band", with a sub-pixel peak estimator, at the camera's frame
rate (compiled kernels, a few passes over the image, no Python loop over pixels).

Two detectors share the sub-pixel estimators: the *ridge* detector (the default, built
for real, ambient-lit frames: issue 10) and the seed's *band* detector as written
(``detector="band"``).

The ridge detector, per frame
-----------------------------
Real laser frames are lit by the room: white and coloured surfaces are as bright as the
stripe, the light varies across the image, the line also falls on the table and the
wall, and the scene is cluttered. The seed's lightness band (eq. 19-20) then selects
white surfaces and room light (a real webcam scan came out 2 mm off). Instead:

1. The laser's colour. A contrast ``k`` of :data:`CONTRASTS`: the laser's own channel
   (red, green or blue) or the lightness (mono images, white lasers). A laser *adds*
   light, mostly of its colour: where it lies its channel rises against the
   neighbourhood, and rises more than the other two channels. So the height of a
   candidate is ``min(x_k, x_k - max(x_o1, x_o2))`` with ``x_c`` the ridge height of
   channel ``c`` (below): a thin white or grey thing rises in all three channels (0), a
   green cable on a white wall falls in all three (< 0), a light joint between red
   tiles rises more in blue than in green (< 0). Where the laser's channel is saturated
   (>= 98 % of full scale) its rise is clipped while the others still rise (a green
   laser on a white board records as (245, 255, 255) on (229, 227, 240) in the real srv
   frames): there it must rise more than *half* the others' rise. Where *both* other
   channels fall, the candidate is no light at all (zero): the ringing of a JPEG edge
   between a coloured object and the table, an object's dark rim (a laser's light is
   never confined to one channel: the filters overlap, JPEG spreads chroma; the real
   srv stripe raises the other channels by 15 levels). Where *one* of them falls, its
   fall is taken off the height: a laser only adds light, and a line where one channel
   falls while the laser's rises is the surface's colour changing (a grey edge on an
   orange block under a blue laser: red -8, green +5, blue +16 levels, height 11 -> 3).
   Measured on the front-end cells (``benchmarks/README.md``, stop 34): points more
   than 1 mm off red 0.31 -> 0.26 %, green 0.006 -> 0.003 %, blue 0.43 -> 0.39 %,
   recall 0.1-0.2 points lower; the real srv board unchanged. A laser raises the luma
   too: the height is at most the luma's ridge height over :data:`_LUMA_SHARE` (a
   JPEG stores the chroma at half resolution: smeared onto the bright side of a colour
   edge it makes a ridge of one channel with no luma ridge, a blue line along every
   edge of a blue object against a white wall), and a candidate whose luma rises less
   than :data:`_EDGE_SHARE` of the luma's step across it is that ringing on the bright
   side of an edge (its small overshoot of the luma, with a fringe of the laser's
   colour: arcs along a yellow checker's edges under a blue laser). The colour is chosen
   once per recording by the stage (:func:`estimate_laser_colour` on 12 spaced frames),
   or per frame with ``colour="auto"``: the contrast in which the stripe is the
   strongest *curve* (step 3) on every 1/48-th row and column; the lightness only when
   it scores 8 times the best colour (it sees every thin bright thing of a room).
   When two colours score within a factor 4 (:func:`laser_colour_contested`) and the
   recording has views, the stage scores the views the same way: a colour whose ridges
   the views show as well is the scene's texture, not the laser
   (:func:`laser_colour_beyond_scene`). The stage does the same where the lightness won
   over a colour that scored (:func:`lightness_contested`: a textured surface under a
   faint, speckled laser). Without views the laser frames check it themselves: the
   laser is rigid with the camera, so its stripe stays put between two frames of a sweep
   where the scene's texture moves with the scene (:func:`laser_colour_by_motion`).
2. Peak against a local baseline: the ridge height of a profile ``y`` across the line is
   ``y(r) - min(max(y(r - 3), y(r + 3)), max(y(r - 6), y(r + 6)))``: both sides lower at
   one of two distances (3 and 6 px: stripes up to ~8 px FWHM at full height), zero on
   a step edge or a gradient of the room light.
3. The stripe is a connected curve. Per line the two strongest candidates at least 7 px
   apart are kept; each is linked to the nearest candidate of the previous lines (up to
   3 lines back) within ``link_px`` px per line; per line the candidate on the strongest
   curve (its summed height; then the longest) wins if that curve spans ``min_run``
   lines (by length, a long faint curve took the stripe's lines: the blue cell's block,
   an edge's faint ridge over 122 lines against the stripe's two pieces of 82 and 84
   lines three times as high, broken where it fades for 4 lines). Rejections are
   counted: ``isolated`` (candidates on shorter curves: glints, texture, dots),
   ``second_line`` (candidates on another long curve in a line that kept the stripe,
   and every line of a curve that loses in more of its lines than it wins: a
   reflection beside the stripe, also where the stripe itself is missing). The line on
   the table or the wall in *other* lines is a curve of its own and is kept: the
   workspace crop of the triangulation removes it.
3b. Hysteresis (``follow``, off by default), as Canny's and Steger's [5] line
   detectors: each kept curve is followed beyond its ends, line by line, within
   1 px per line of the position its direction predicts, with a weaker test
   (:func:`_weak_at`): the laser channel's two-sided rise less *half* the other
   channels' rise, the pixel itself of the laser's colour (its channel ``min_peak``
   above the others: not a grey wall, not white), and the rise at least a quarter of
   the step across the pixel (not a JPEG's ringing beside an edge); it also takes a
   line won by another curve where it is twice that winner's height by the same test.
   Why: in a 4:2:0 JPEG a thin stripe keeps little of its colour (the chroma is
   stored at half resolution): on an object of the laser's own colour its rise is
   nearly the same in all three channels, so the scan's test rejects it (53 % of the
   missed true stripe pixels of the simulated green cell). Measured on the simulated
   cells: recall 0.890 -> 0.940 (green), 0.959 -> 0.962 (red), 0.927 -> 0.931 (blue).
   The added points near the silhouettes moved the blue cell's alignment (delivered p95
   0.19 -> 0.68 mm), which the refinement's second start from the robot's poses undoes
   since stop 31 (p95 0.173 mm); but a tenth of what it adds on the red and blue cells
   lies more than 1 mm off (points more than 1 mm off: red 0.50 -> 0.55 %, blue 0.65 ->
   0.71 %), hence off (``benchmarks/results/front_end.json``).
4. The axis, per frame, from the stripe's geometry: the probe of step 1 on sampled rows
   (profiles along u: a stripe crossing the rows) and columns; the axis whose strongest
   curve is stronger (a stripe within 45 degrees of vertical gets one centre per row).
   A stripe bent into a U (the laser's arc inside a cup) runs both ways, and the
   probe's strongest curve can be one of its steep arms: where the chosen axis crosses
   two curves in far more lines than it kept (``two_blobs`` and ``second_line``, three
   times the centres), the other axis is searched too and kept when it finds more
   centres and crosses two curves in fewer lines than it keeps. The stripe's direction
   ``angle_deg`` is the median slope between centres of neighbouring lines.
   The stage fixes the axis from the laser's geometry instead where it can
   (``stripes.axis_from_laser_within_deg``, 30 by default,
   :func:`robo3d.triangulation.epipolar_axis`):
   each ray of the sheet lights one point, so the stripe crosses each of the laser's
   epipolar lines once, and where those run within that angle of the columns (rows) a
   bright line along the columns (rows) cannot be the stripe. On random scene 142's black
   vase over ArUco markers (a monochrome camera, the stripe barely visible on black) the
   probe took the markers' vertical gaps in 10 of 40 frames, 98 % of their points more
   than 1 mm off; with the laser's axis the points in the box more than 1 mm off fall
   from 211 to 97 (``tests/test_epipolar_axis.py``); a blue laser on a yellow striped
   blob, whose frames took the stripes' edges, measured 0.93 mm instead of 2.04 mm. The
   cost: where the stripe grazes the surface (a cup's inner rim) it runs nearly along
   the epipolar lines, and one centre per such line is ill-defined there; on the objects
   benchmark's cup/7 two such frames (of 817) moved two sweeps' alignment by 0.1 mm, and
   the blue cell's points more than 1 mm off rose from 0.39 to 0.47 %
   (``benchmarks/README.md``, stops 35 and 36).
5. The sub-pixel centre is the band detector's (step 5 below) on the profile of the
   laser's own channel (flat-topped, still centred, where it saturates; a chroma
   difference would dip there) or the lightness, around the winning candidate's
   brightest pixel within 2 px, with a *linear* local baseline: the line through the
   minima of the 3-pixel running mean on either side (a gradient does not bias it),
   each side's minimum taken only up to an edge beyond the stripe's foot (a new low
   after the profile has levelled out: a checker's dark square 7 px beside the stripe
   otherwise tilted the baseline and moved the centre up to 4 px onto the grey face on
   the other side, :func:`_side_background`).
   With ``centre_on="luma"`` the centre is taken on the profile of the luma
   ``Y = 0.299 R + 0.587 G + 0.114 B`` instead, where that profile has a peak of its own
   within 1.5 px (else the laser channel's centre stays): a JPEG that stores colour at
   half resolution (4:2:0, 4:2:2: what webcams and most encoders write) keeps the
   laser's channel mostly in its blurred, half-sampled chroma, whose centre moves with
   the stripe's phase on the 2-pixel chroma grid, while the luma is stored at full
   resolution (``tests/test_jpeg_centres.py`` measures both). The pipeline chooses it
   per recording from the JPEG header (``stripes.centre_on: auto``).
5b. A centre wider than ``max_width_rel`` times the median width of its frame's centres
   (with at least :data:`_WIDE_MIN_CENTRES` of them) is dropped and counted ``too_wide``:
   where a faint stripe runs along an edge beside a face lit as brightly in the laser's
   channel (the blue cell's block: its blue front face under the stripe on its top
   edge), the run above the tail threshold spreads over the face and the centre moves
   onto it, 11-14 px wide against 2-4 px, 4-6 px off the line. At 3 times the median:
   points more than 1 mm off red cell 0.503 -> 0.467 %, blue cell 0.654 -> 0.580 %;
   on the objects benchmark's grey objects, where a stripe seen obliquely is wide and
   right, at most 0.06 % of the points go (all within 0.3 mm of the truth); twice the
   median took up to 1.1 % there. Off by default (``max_width_rel: 0``): some of the
   wide centres it drops are the grazing profiles' outermost points, which the
   alignment's silhouette term uses, and the alignment moved with them: on the hard
   scenes with poor masks the green-laser white cup's worst sweep went 0.67 -> 1.37 mm
   and its measured p95 0.157 -> 0.310 mm (``benchmarks/README.md``, stop 31). Step 5c
   tells those centres apart better, and is applied after the alignment.
5c. Each centre's skew (:attr:`StripePoints.skew_px`): its distance from the middle of
   its profile's top (the laser channel's pixels around the brightest one within
   :data:`_TOP_FRACTION` of the peak height). A stripe's centre lies at its top however
   wide (seen obliquely) or flat (saturated) the stripe is; a run spread over a face
   beside the stripe (the case of step 5b: a shoulder that fades over 10 px pulls the
   centre 3 px) or a reflection merging into it pulls the centre away from the top. The
   detector only reports it; the align stage drops the aligned points whose centre lies
   more than ``alignment.max_centre_skew_px`` (2) from its top, after the alignment,
   which uses the grazing profiles' outermost points. Measured: on the front-end
   benchmark's cells the points more than 1 mm off have a median skew of 1.5-2.4 px,
   the points within 0.3 mm a 99th percentile of 0.6-0.7 px; on the real desktop
   scanner's boards 90 % of the centres skewed more than 2 px are off the laser plane,
   0.03 % of the rest (``benchmarks/README.md``, stop 32).
6. Confidence: the SNR term and the width term below, a contrast term (the peak over the
   frame's median peak, capped at 1) and a curve term (its length over ``2 min_run``,
   capped at 1). ``s`` (eq. 18) is reported on the centres' pixels.
7. Threshold: ``max(min_peak, 6 sigma)`` with ``sigma`` the contrast's noise (step 7
   below).

8. Region of interest (``roi``, optional): where the stripe can be. The stage passes
   the image region where the laser sheet inside the recording's workspace box
   projects, grown by ``stripes.roi_margin_px``
   (:func:`robo3d.triangulation.sheet_in_workspace`,
   :func:`robo3d.triangulation.sheet_roi_mask`): a stripe point elsewhere cannot
   triangulate into the box, so the workspace crop would drop it anyway, but outside
   the region it can still beat the stripe (an orange object's lit rim, the line on the
   wall) and vote for the wrong colour. Candidates are taken only in each line's span
   of the region (between its first and last pixel: exact for the convex region of a
   sheet in a box), in the colour vote, the axis probe and the scan alike; the heights
   still read the pixels beyond it. Lines that miss the region are counted
   ``outside_roi``. In a line, a candidate on a long curve that is more than twice as
   high as the other wins even where the other lies on a stronger curve: an object's lit
   rim meets the stripe at the silhouette and the two link into one long curve (the
   simulated orange vase). What the region cannot remove: an object's lit rim or edge
   of the laser's colour inside the sheet's band in frames where the sheet misses the
   object there (no stripe in the line to beat it): the remaining outliers of the
   simulated cells. Such points lie in free space (on the cone of rays
   that graze the object); a test against the other frames' rays or the visual hull
   would remove them, the detector alone cannot. Without the region the line on the
   table or the wall (outside the box) wins those lines and the crop drops it, which
   hides the rim: the region costs some outliers and gains recall where that line would
   beat the stripe (the figures: ``benchmarks/README.md``, "Notes moved from
   robo3d/stripes.py").

9. A faint stripe in a noisy frame (``faint_taps``, 5 by default): where the frame's
   noise sets the threshold well above ``min_peak`` (``6 sigma > 1.5 min_peak``, sigma
   of the laser's channel or the mono frame, interpolated within the integer levels: a
   cheap sensor, a dark object, a laser the object barely reflects) the frame is
   searched again averaged over ``faint_taps`` pixels along its lines (a matched filter
   along the stripe: a straight stripe keeps its height, the noise falls by
   ``sqrt(faint_taps)``, and so does the threshold; the mean at three slopes, the largest
   per pixel and channel: an RGB frame's other channels at least as high as at the
   stripe's slope, so its colour test is not loosened), with curves at least twice
   ``min_run`` long, along the first search's axis and in its colour. Its centres in
   the lines the first search left without one are added, confidence scaled by
   ``1 / sqrt(faint_taps)`` and flagged (``StripePoints.faint``), except those on
   texture (their 7 x 7 neighbourhood's standard deviation over 6 sigma: a faint stripe
   adds about 3; counted ``textured``) (:func:`_faint_stripe`; the stage reports
   ``faint_points`` and ``frames_with_faint_points``). Not for the lightness of an RGB
   frame (a white laser).

Cost: one pass over the image reads the laser's channel (or the lightness) of each row
once, into a ring of 13 rows (one centre per column) or a row buffer (per row: no
transpose), computes the heights in vectorised loops and updates a line's candidates
only where a height beats its second (blocks of 32 are skipped by a vectorised test);
the other channels are read only there. Clutter adds only those rare updates: a busy
frame costs about what a clean one does. On uint8
frames (a laser colour, or mono: what cameras record) the scans and the axis probe run
in byte arithmetic (:func:`_lines8`, :func:`_ridge_scan_cols8`: the laser's channel
read at literal offsets, saturating heights of 32 pixels per instruction, the pixels
whose height beats the line's second candidate found 8 bytes at a time, a pixel on the
best ridge that is not above it passed over), the probe's sampled columns are gathered
in one pass over the rows, and everything after the choice of colour is one compiled
call that holds no interpreter lock (:func:`_ridge_frame8`, :func:`_ridge_tail8`), so
frames scale over threads; the results are identical to the generic kernels'.
``benchmarks/laser.py`` measures the cost (the figures: ``benchmarks/README.md``).

Choices where issue 10 leaves room: the two-candidate limit (a third, stronger clutter
ridge in a line hides the stripe there: counted ``too_weak`` or ``isolated``); the
colour is not chosen from eq. 18 samples but from where the stripe is consistent
(samples need the stripe first); ``min_peak`` default 8 grey levels (the real board's
saturated stripe rises 13 levels).

The band detector (the seed as written), per frame
--------------------------------------------------
1. Lightness ``L`` (seed eq. 19): ``L = (max(R, G, B) + min(R, G, B)) / 2``; a mono image
   is its own lightness. When a laser-off ``background`` frame is given, the frame is
   first replaced by ``max(image - background, 0)`` channel by channel.
2. Samples of the laser line. The seed lets a user click points of the line; we take,
   in every line (column, or row), its brightest pixel, and keep the lines where that
   pixel stands at least ``min_peak`` above the line's darkest pixel — the pixels a user
   would click along the stripe. The frame's brightness coefficient ``s`` (seed eq. 18)
   is the mid-range of the mean R, G, B of these samples (with a laser-off background,
   of the difference image). A caller may instead pass ``s`` (the user's choice).
3. Reference brightness of each line and the band mask ``I_b`` (seed eq. 20):
   ``(1 - band) s_ref <= L <= (1 + band) s_ref``.

   * ``reference="frame"`` — the seed as written: ``s_ref = s`` for every line.
   * ``reference="local"`` (default) — ``s_ref`` is the median of the sampled peaks of
     the lines within ``±reference_lines`` of the line, capped by the line's own peak.

   Why the local reference: the stripe's brightness is not uniform. It falls with the
   cosine of the incidence angle, the albedo and the range, by a factor of 2–10 across
   one frame of our demo recordings; a ±15 % band around one frame-wide ``s`` then
   drops every column where the stripe is dimmer (on the demo's vase, half of the
   stripe in many frames) and whole frames at the sweeps' ends, where the stripe
   crosses only a rim of the object and the frame's brightest pixels are the table's
   stripe (ten times dimmer, below ``min_peak``: the frame's ``s`` is then too small and
   nothing is found). The local median follows the stripe along the frame, still keeps
   the seed's band where it matters — a white highlight brighter than
   ``(1 + band) s_ref`` beside the stripe is ignored, a second blob inside the band is a
   reflection — and the cap keeps a line dimmer than its neighbours (an albedo edge)
   inside its own band. The absolute floor ``min_peak`` (above the local background)
   stays: it rejects the table's stripe, noise and ambient texture.
4. Locating the stripe in a line. A *blob* is a contiguous run of ``L >= (1 - band)
   s_ref``. The stripe is the blob around the line's brightest band pixel (or, when no
   pixel of the line is in the band, around its brightest pixel). A second blob that
   holds band pixels makes the line ambiguous (a reflection of the sheet): rejected. A
   blob brighter than the band everywhere beside a band blob is ignored (a highlight,
   which is what the band's upper bound is for); alone in its line it is the stripe (a
   stripe brighter than ``(1 + band) s``, whose flanks may jump over the band between
   two samples).
5. Sub-pixel centre ("associate a line to the band"). Around the blob's brightest pixel
   ``p`` a window of ±8 pixels is read; when it cannot hold the stripe (fewer than 3
   pixels beyond the run of ``y > T`` on a side, or a half-maximum crossing outside it)
   it is read again over ``±h`` (``h = ceil(1.1 max_width_px) + 2``), so
   narrow stripes cost little and wide ones are still measured whole. The local
   background ``b`` is the minimum of the window's 3-pixel running mean, so a bright
   feature on one side does not raise it. With ``y = L - b``, amplitude ``A = y(p)`` and a
   tail threshold ``T = max(tail_fraction * A, noise_k * sigma_noise)``, the centre is the
   centre of gravity of the soft-thresholded profile ``max(y - T, 0)`` over the
   contiguous run around ``p`` where ``y > T``. The weights fall continuously to zero at
   the run's ends, so the estimate stays unbiased (below 0.01 px on a sampled Gaussian)
   even where the band clips the peak — the band only finds the run, it is never the
   weight. ``method="gaussian"`` instead fits a parabola to ``ln y`` over the same run by
   least squares with weights ``y²`` (Guo 2011): the 3-point Gaussian estimator when the
   run is three pixels long, exact for a noise-free Gaussian, less noisy than the
   3-point form on wide stripes; it falls back to the centre of gravity where the fit is
   not defined (fewer than three pixels, a flat saturated top, a vertex off the peak).
6. Rejections, each line counted once, under the first reason that applies:
   ``too_weak`` (the line's peak stands less than ``min_peak`` above its darkest pixel),
   ``no_band`` (nothing reaches the band's lower edge), ``too_wide`` (the blob is wider
   than the window), ``two_blobs``, ``too_weak`` (``A`` below ``min_peak`` above the local
   background), ``too_wide`` (the run fills the window), ``at_border`` (the run is cut
   by the image border: the centre would be biased), ``too_wide`` (full width at half
   maximum above ``max_width_px``).
7. Confidence in [0, 1]: the product of an SNR term ``1 - exp(-A / (10 sigma_noise))``,
   a width term (1 up to half of ``max_width_px``, falling linearly to 0 at it) and a
   contrast term ``min(1, A / ((1 - band) s))`` with the frame's ``s`` (a stripe much
   dimmer than the frame's typical stripe is less certain). ``sigma_noise`` is the
   frame's noise, estimated robustly from the median absolute difference of
   neighbouring pixels along the lines (Donoho's MAD estimator on first differences),
   on a fixed subsample of about 4 000 pixel pairs.

Speed
-----
The work is done by Numba-compiled kernels (``nogil``, cached on disk), written so that
their inner loops vectorise (branch-free updates, integer compares on integer images):
one pass over the image for the lines' peaks and the rows' extrema, one pass counting the
band's pixels per line over the rows that can reach a band (the others are skipped), then
``O(window)`` work per line (``benchmarks/laser.py`` times it); since the kernels release
the GIL, :func:`extract_stripes_batch` and the pipeline's stage run frames on several
threads. The first call of a process compiles the kernels (once; later processes load
them from Numba's cache).

A stripe narrower than about 1.2 px (full width at half maximum) is *pixel locked*: the
sensor integrates it over one or two pixels and its position inside the pixel is lost,
for either estimator; from 1.5 px on both are unbiased. The optics should spread the
stripe over 1.5 px or more (the simulated one is 1.5-1.7 px wide at 640 x 480).

Choices where the seed is vague
-------------------------------
* The seed's image is RGB and the laser red; we accept any laser colour (eq. 19 is
  colour-blind) and mono images.
* Images are read in their own units (grey levels for integer images); ``min_peak`` is
  in those units (the config's ``stripes.min_peak``, default 8, is in grey levels of
  8-bit images); ``min_peak=None`` is 4 % of the full scale (255 for uint8, 65535 for
  uint16, 1.0 for float images).
* ``axis="columns"`` gives one centre per column: ``u`` is the (integer) column and
  ``v`` the sub-pixel row. ``axis="rows"`` gives one centre per row; ``axis="auto"``
  (the default, for both detectors) picks it per frame from the stripe's geometry
  (step 4 of the ridge detector, on the lightness for the band detector), not from the
  number of lines whose peak stands ``min_peak`` above their darkest pixel (room light
  lifts every line).
* The parameters are one :class:`StripeOptions`, made from the config's ``stripes``
  section (``StripeOptions.from_config(cfg["stripes"])``); the image, its laser-off
  frame and its region of interest are per call.
* Images with another number of channels than 1 or 3, booleans or non-finite floats are
  refused; integer types other than uint8/uint16 and float64 are read as float32.

References
----------
.. [1] The seed chapter, "Robot assisted 3D shape acquisition by optical systems", §4.2,
   eqs. 18–20.
.. [2] R. B. Fisher and D. K. Naidu, "A comparison of algorithms for subpixel peak
   detection", in Image Technology, Springer, 1996 (centre of gravity, Gaussian
   3-point fit).
.. [3] H. Guo, "A simple algorithm for fitting a Gaussian function", IEEE Signal
   Processing Magazine 28(5), 2011.
.. [4] D. L. Donoho and I. M. Johnstone, "Ideal spatial adaptation by wavelet
   shrinkage", Biometrika 81(3), 1994 (the MAD noise estimate).
.. [5] C. Steger, "An unbiased detector of curvilinear structures", IEEE TPAMI 20(2),
   1998.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numba import njit

from .options import Options

__all__ = [
    "CONTRASTS",
    "StripeOptions",
    "StripePoints",
    "centre_on_for",
    "skewed_centres",
    "REJECTION_REASONS",
    "brightness_coefficient",
    "lightness",
    "estimate_laser_colour",
    "image_level",
    "laser_colour_beyond_scene",
    "laser_colour_by_motion",
    "laser_colour_contested",
    "lightness_contested",
    "scene_motion",
    "extract_stripe_centres",
    "extract_stripes_batch",
]

log = logging.getLogger(__name__)

#: Reasons a line (column or row) yields no centre, as counted in
#: :attr:`StripePoints.rejected`.
REJECTION_REASONS: tuple[str, ...] = (
    "no_band",
    "two_blobs",
    "too_weak",
    "too_wide",
    "at_border",
    "isolated",
    "second_line",
    "outside_roi",
    "textured",
)

_Axis = Literal["columns", "rows", "auto"]


@dataclass
class StripePoints:
    """The stripe centres found in one frame, one per image line at most.

    Attributes
    ----------
    u, v : (N,) float64, pixels
        Sub-pixel stripe centres (column, row), origin at the centre of the top-left
        pixel. With ``axis="columns"`` ``u`` is the integer column and ``v`` sub-pixel.
    confidence : (N,) float64 in [0, 1]
        Heuristic quality of each centre (SNR, width, contrast); ones when not given.
    peak : (N,) float64
        Peak height above the local background, in lightness units of the image.
    width_px : (N,) float64, pixels
        Full width at half maximum of the stripe across the line.
    skew_px : (N,) float64, pixels
        The centre's signed distance across the line from the middle of its profile's
        top (the pixels within 5 % of the peak height around the brightest one; the
        laser channel's profile). A symmetric stripe's centre lies at its top, however
        wide or flat; a centre pulled away from it is an asymmetric run: the stripe
        along an edge beside a face lit as brightly in the laser's channel, its run
        spread over the face (module docstring, step 5c). NaN when not known.
    line : (N,) int64
        Index of the line each centre belongs to: the column for ``axis="columns"``,
        the row for ``axis="rows"``. Defaults to the rounded ``u`` (or ``v``).
    axis : str
        ``"columns"`` or ``"rows"``: the direction the centres were searched in. When
        not given (None), inferred from the centres: ``"rows"`` if every ``v`` is an
        integer and some ``u`` is not, else ``"columns"`` — so a frame rebuilt from
        stored ``u, v`` keeps its lines.
    s : float
        The brightness coefficient (seed eq. 18) used.
    n_lines : int
        Number of lines examined.
    rejected : dict of str to int
        Lines that gave no centre, by reason (keys :data:`REJECTION_REASONS`); for the
        ridge detector ``isolated`` and ``second_line`` also count the candidates dropped
        in lines that kept a centre (see :func:`extract_stripe_centres`).
    angle_deg : float, degrees
        Direction of the stripe in the image, from the ``u`` axis towards ``v``, in
        (-90, 90] (90: a vertical stripe); the principal axis of the centres (NaN with
        fewer than two).
    colour : str
        The contrast the stripe was found in (:data:`CONTRASTS`: a laser colour or
        ``"lightness"``), or ``""`` when not known.
    faint : (N,) bool
        The centre was found in the frame averaged along the stripe, in a line the first
        search left without one (a faint stripe in a noisy frame: module docstring,
        step 9); the rejection counts are the first search's (and ``textured``). All
        false when not given.
    v_sensor : (N,) float64 or None, pixels
        The row on the sensor where each centre was found, where it is not ``v``: a
        rectified camera's centres are found in the raw frame and moved to the pinhole
        camera (``robo3d.camera.Rectifier``), and a rolling shutter exposes the raw rows
        one after the other. None: ``v`` is the sensor's row.
    """

    u: np.ndarray
    v: np.ndarray
    confidence: np.ndarray | None = None
    peak: np.ndarray | None = None
    width_px: np.ndarray | None = None
    line: np.ndarray | None = None
    axis: str | None = None
    s: float = float("nan")
    n_lines: int = 0
    rejected: dict[str, int] = field(default_factory=lambda: dict.fromkeys(REJECTION_REASONS, 0))
    angle_deg: float = float("nan")
    colour: str = ""
    skew_px: np.ndarray | None = None
    faint: np.ndarray | None = None
    v_sensor: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.u = np.asarray(self.u, dtype=np.float64).reshape(-1)
        self.v = np.asarray(self.v, dtype=np.float64).reshape(-1)
        n = self.u.size
        if self.v.size != n:
            raise ValueError(f"u and v must have the same length, got {n} and {self.v.size}")
        if self.axis is None:
            int_u = bool(np.all(self.u == np.rint(self.u)))
            int_v = bool(np.all(self.v == np.rint(self.v)))
            self.axis = "rows" if (int_v and not int_u) else "columns"
        if self.axis not in ("columns", "rows"):
            raise ValueError(f"axis must be 'columns' or 'rows', got {self.axis!r}")

        def _vec(x: np.ndarray | None, default: float, name: str) -> np.ndarray:
            if x is None:
                return np.full(n, default, dtype=np.float64)
            x = np.asarray(x, dtype=np.float64).reshape(-1)
            if x.size != n:
                raise ValueError(f"{name} must have {n} entries like u, got {x.size}")
            return x

        self.confidence = _vec(self.confidence, 1.0, "confidence")
        self.peak = _vec(self.peak, np.nan, "peak")
        self.width_px = _vec(self.width_px, np.nan, "width_px")
        self.skew_px = _vec(self.skew_px, np.nan, "skew_px")
        self.faint = (np.zeros(n, np.bool_) if self.faint is None
                      else np.asarray(self.faint, dtype=np.bool_).reshape(-1))
        if self.faint.size != n:
            raise ValueError(f"faint must have {n} entries like u, got {self.faint.size}")
        if self.v_sensor is not None:
            self.v_sensor = _vec(self.v_sensor, np.nan, "v_sensor")
        if self.line is None:
            along = self.u if self.axis == "columns" else self.v
            self.line = np.rint(along).astype(np.int64) if n else np.zeros(0, np.int64)
        else:
            self.line = np.asarray(self.line, dtype=np.int64).reshape(-1)
            if self.line.size != n:
                raise ValueError(f"line must have {n} entries like u, got {self.line.size}")
        full = dict.fromkeys(REJECTION_REASONS, 0)
        full.update({k: int(c) for k, c in self.rejected.items()})
        self.rejected = full

    def __len__(self) -> int:
        return int(self.u.size)

    @property
    def pixels_uv(self) -> np.ndarray:
        """The centres as ``(N, 2)`` float64 ``(u, v)`` pixels."""
        return np.stack([self.u, self.v], axis=-1)

    @classmethod
    def empty(cls, *, axis: str = "columns", s: float = float("nan"), n_lines: int = 0,
              rejected: dict[str, int] | None = None, colour: str = "") -> StripePoints:
        """A frame without any centre."""
        z = np.zeros(0)
        return cls(z, z, axis=axis, s=s, n_lines=n_lines,
                   rejected=dict(rejected or {}), colour=colour)


@dataclass(frozen=True)
class StripeOptions(Options):
    """The stripe detector's parameters: the config's ``stripes`` keys that
    :func:`extract_stripe_centres` uses, under the same names, and two estimator
    constants that are not in the config (``not_in_config``).

    The section's other keys (``laser_off_topic``, ``roi_from_workspace``,
    ``roi_margin_px``) are the stage's: which laser-off frame and which region of interest
    go with a frame. The stage resolves ``colour="auto"`` once per recording
    (:func:`estimate_laser_colour`) and ``centre_on="auto"`` from the frames' encoding
    (:func:`centre_on_for`) with :meth:`replace`.

    Attributes
    ----------
    detector : {"ridge", "band"}
        ``ridge`` (default): the stripe as a connected ridge of the laser's colour
        contrast (see the module docstring); ``band``: the seed's eq. 20 band on the
        lightness (``band``, ``s``, ``reference`` apply to it only).
    colour : {"auto", "red", "green", "blue", "lightness"}
        The ridge detector's contrast image: a channel's excess over the other two, or
        the lightness; ``auto`` chooses per frame the one in which the stripe is the
        most consistent ridge. Mono images always use their own values.
    min_run : int, lines
        Ridge detector: the shortest connected piece of stripe kept.
    link_px : float, pixels
        Ridge detector: largest step of the stripe between neighbouring lines (per line
        of a gap) for the two to belong to one curve.
    band : float
        Half-width of the brightness band of eq. 20 relative to the reference (0.15 in
        the seed).
    method : {"cog", "gaussian"}
        Centre of gravity of the background-subtracted, soft-thresholded run, or the
        Gaussian (weighted log-parabola) fit over the same run.
    axis : {"columns", "rows", "auto"}
        One centre per column (stripe roughly horizontal), per row, or chosen per frame
        from the stripe's direction.
    min_peak : float or None, the image's units (grey levels for integer images)
        Smallest accepted peak height above the local background. None: 4 % of the full
        scale (10.2 for uint8, 2621.4 for uint16, 0.04 for float images).
    max_width_px : float, pixels
        Largest accepted full width at half maximum across the line.
    max_width_rel : float
        Ridge detector: a centre wider than this many times the median width of its
        frame's centres is dropped (``too_wide``; module docstring, step 5b); 0 (the
        default): no test.
    reference : {"local", "frame"}
        The brightness the band of eq. 20 is centred on, per line: the median of the
        neighbouring lines' peaks capped by the line's own (``local``), or the frame's
        ``s`` (``frame``, the seed as written).
    reference_lines : int, lines
        Half-width of the neighbourhood of the local reference.
    s : float or None
        Brightness coefficient (eq. 18) chosen by the caller, as the seed's user does;
        it is then the reference of every line (``reference`` is ignored). None: ``s``
        is computed from the lines' brightest pixels.
    centre_on : {"laser", "luma", "auto"}
        Ridge detector, RGB frames: the profile of the sub-pixel centre, the laser's
        channel or the luma (for JPEGs with subsampled chroma; module docstring, step 5).
        ``auto`` is the stage's choice from the frames' encoding; an array carries none,
        so :func:`extract_stripe_centres` takes it as the laser's channel.
    follow : bool
        Ridge detector: follow each kept curve beyond its ends where the stripe's colour
        fades (hysteresis, module docstring step 3b). Off by default (the measured
        trade-off: ``benchmarks/results/front_end.json`` notes).
    faint_taps : int
        Ridge detector, frames whose noise sets the threshold (mono, or the laser's
        channel): the frame is searched again averaged over this many pixels along the
        stripe (odd; an even count is taken as the next odd one), for a faint stripe
        (module docstring, step 9); 0 or 1: not.
    tail_fraction : float
        Soft threshold of the centre of gravity, relative to the peak height (not in the
        config).
    noise_k : float
        The soft threshold is at least ``noise_k`` times the frame's noise sigma (not in
        the config).
    """

    section = "stripes"
    not_in_config = ("tail_fraction", "noise_k")

    detector: Literal["ridge", "band"] = "ridge"
    colour: str = "auto"
    min_run: int = 8
    link_px: float = 3.0
    band: float = 0.15
    method: Literal["cog", "gaussian"] = "cog"
    axis: _Axis = "auto"
    min_peak: float | None = 8.0
    max_width_px: float = 15.0
    max_width_rel: float = 0.0
    reference: Literal["local", "frame"] = "local"
    reference_lines: int = 16
    s: float | None = None
    centre_on: Literal["laser", "luma", "auto"] = "auto"
    follow: bool = False
    faint_taps: int = 5
    tail_fraction: float = 0.05
    noise_k: float = 3.0


# ---------------------------------------------------------------------------- helpers
def _check_image(image: np.ndarray, name: str = "image") -> np.ndarray:
    if not isinstance(image, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(image).__name__}")
    ok_shape = image.ndim == 2 or (image.ndim == 3 and image.shape[2] == 3)
    if not ok_shape:
        raise ValueError(f"{name} must be (H, W) mono or (H, W, 3) RGB, got shape "
                         f"{image.shape} {image.dtype}")
    if image.dtype == np.bool_ or not (np.issubdtype(image.dtype, np.integer)
                                       or np.issubdtype(image.dtype, np.floating)):
        raise ValueError(f"{name} must be an integer or float image, got {image.dtype}")
    return image


def _full_scale(dtype: np.dtype) -> float:
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    return 1.0


def _subtract_background(image: np.ndarray, background: np.ndarray | None,
                         pedestal: bool = False) -> np.ndarray:
    """``max(image - background, 0)`` (or the image itself when no background), in the
    image's own type when that is an integer type (the difference of two frames lies
    between 0 and the image, rounded when the background is a float mean).

    Why its own type: the detector reads the saturation level and the fast 8-bit kernels
    off the image's type. Handed as float32 (full scale 1.0), a laser-off-subtracted
    8-bit frame counted every pixel above 0.98 as saturated, where the colour test takes
    only half of the other channels' rise: a thin white line that was not in the
    laser-off frame (a cable moved, a glint) passed as the stripe where the stripe was
    occluded (``tests/test_stripes_background.py``). The saturation test on the
    difference is conservative: a channel clipped at 255 over a background of 100 reads
    155, not saturated, so only its rise above the others counts.

    With ``pedestal`` (the detector's input) the difference is not clipped at zero but
    lifted by an eighth of the full scale (32 for 8 bits; a float image is left
    unclipped): the difference of two frames is noise of either sign where nothing
    changed, and clipped at zero, half of its pixels were 0 and the detector's noise
    estimate half the true one (simulated mono cell over printed dots: 2.1 against
    5.2 DN), so that ridges of noise passed as the stripe in frames where it was short.
    The detector measures every height against a local baseline: the pedestal moves
    none of them."""
    if background is None:
        return image
    background = _check_image(np.asarray(background), "background")
    if background.shape != image.shape:
        raise ValueError(f"background must have the image's shape {image.shape}, got "
                         f"{background.shape}")
    diff = image.astype(np.float32) - background.astype(np.float32)
    integer = np.issubdtype(image.dtype, np.integer)
    if pedestal and not integer:
        return diff
    if pedestal:
        diff += np.float32(np.iinfo(image.dtype).max // 8 + 1)
    np.clip(diff, 0.0, np.iinfo(image.dtype).max if integer else None, out=diff)
    if integer:
        return np.rint(diff).astype(image.dtype)
    return diff


def lightness(image: np.ndarray) -> np.ndarray:
    """Lightness of an image, seed eq. 19: ``L = (max(R, G, B) + min(R, G, B)) / 2``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        Mono or RGB image (channel order does not matter: eq. 19 is symmetric).

    Returns
    -------
    (H, W) float32
        Lightness in the image's own units; a mono image is returned as float32.

    References
    ----------
    .. [1] The seed chapter, §4.2, eq. 19 (the HSL lightness).
    """
    image = _check_image(np.asarray(image))
    if image.ndim == 2:
        return image.astype(np.float32)
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    # channel-wise maximum/minimum: much faster than reducing over the last axis
    out = np.maximum(np.maximum(r, g), b).astype(np.float32)
    out += np.minimum(np.minimum(r, g), b)
    out *= 0.5
    return out


def _sample_mask(sample: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    sample = np.asarray(sample)
    if sample.dtype == np.bool_:
        if sample.shape != shape:
            raise ValueError(f"sample mask must be (H, W) = {shape} bool, got {sample.shape}")
        return sample
    if sample.ndim != 2 or sample.shape[1] != 2:
        raise ValueError(f"sample must be an (H, W) bool mask or (N, 2) pixels (u, v), got "
                         f"shape {sample.shape} {sample.dtype}")
    uv = np.rint(np.asarray(sample, dtype=np.float64)).astype(np.int64)
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < shape[0])
    if not np.all(inside):
        bad = uv[~inside][0]
        raise ValueError(f"sample pixel (u, v) = ({bad[0]}, {bad[1]}) is outside the "
                         f"{shape[1]}x{shape[0]} image")
    mask = np.zeros(shape, dtype=bool)
    mask[uv[:, 1], uv[:, 0]] = True
    return mask


def _brightness(image: np.ndarray, L: np.ndarray, sample: np.ndarray | None,
                top_fraction: float) -> float:
    h, w = L.shape
    if h * w == 0:
        return 0.0
    if sample is not None:
        mask = _sample_mask(sample, (h, w))
        if not mask.any():
            raise ValueError("sample selects no pixel")
    else:
        if not (0.0 < top_fraction <= 1.0):
            raise ValueError(f"top_fraction must be in (0, 1], got {top_fraction}")
        n = max(1, int(round(top_fraction * h * w)))
        flat = L.reshape(-1)
        thr = np.partition(flat, flat.size - n)[flat.size - n]
        mask = L >= thr
    if image.ndim == 2:
        means = np.array([float(image[mask].astype(np.float64).mean())])
    else:
        means = image[mask].astype(np.float64).mean(axis=0)
    return float((means.max() + means.min()) / 2.0)


def brightness_coefficient(
    image: np.ndarray,
    *,
    sample: np.ndarray | None = None,
    top_fraction: float = 0.002,
    background: np.ndarray | None = None,
) -> float:
    """Brightness coefficient ``s`` of the laser line, seed eq. 18.

    ``s = (max(mean R, mean G, mean B) + min(mean R, mean G, mean B)) / 2`` over samples
    of the laser line. The seed's user clicks the samples; by default we take the
    ``top_fraction`` brightest pixels of the frame by lightness (eq. 19), or of the
    laser-on minus laser-off difference when ``background`` is given.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        The laser-lit frame (mono: R = G = B).
    sample : (H, W) bool or (N, 2) float, optional
        The samples: a mask, or pixels ``(u, v)`` (rounded to the nearest pixel).
    top_fraction : float
        Fraction of the frame's pixels taken as samples when ``sample`` is None
        (at least one pixel).
    background : same shape as ``image``, optional
        A laser-off frame; the samples and the means are taken on
        ``max(image - background, 0)``.

    Returns
    -------
    float
        ``s`` in the image's units (0.0 for an image without pixels).

    References
    ----------
    .. [1] The seed chapter, §4.2, eq. 18.
    """
    image = _check_image(np.asarray(image))
    image = _subtract_background(image, background)
    return _brightness(image, lightness(image), sample, top_fraction)


# ---------------------------------------------------------------------------- kernels
# Line status codes of the kernels: 0 = a centre, else 1 + index in REJECTION_REASONS.
(_OK, _NO_BAND, _TWO_BLOBS, _TOO_WEAK, _TOO_WIDE, _AT_BORDER, _ISOLATED, _SECOND,
 _OUTSIDE) = range(9)
_JIT = {"nogil": True, "cache": True}
# The small helpers below are plain ``@njit`` functions, not ``inline="always"``: numba's
# own inlining copied each into every kernel's IR once per argument types, and compiling
# the detector took 100 s of a cold cache on a 2-core Intel Xeon; as functions of their
# own (LLVM still inlines them) 34 s, the same centres bit for bit at the same speed
# (stop 55, ``benchmarks/README.md``).
#: A laser adds light: its luma (Rec. 601) rises by at least this fraction of its
#: channel's rise (a candidate's height is at most the luma's two-sided rise over this).
#: The laser's own share is 0.24-0.29 for a real blue or violet laser on a Bayer sensor
#: (its green and red spill), 0.37 / 0.37 / 0.69 for the simulator's red / blue / green;
#: a JPEG's chroma smeared onto the bright side of a colour edge is a coloured ridge
#: with no luma ridge (the blue cell's block against the white wall: blue +26, luma +2).
_LUMA_SHARE = 0.25
#: A candidate whose luma rises less than this share of the luma's step across it is a
#: JPEG's ringing beside an edge, not light (:func:`_laser_at`). Random scene 907 (a blue
#: laser on a yellow checker sphere, the stripe all but invisible): arcs of centres along
#: the squares' edges, luma +4 beside a step of 41 (0.10). At 0.15 the simulated cells
#: lose 0.02-0.4 points of recall and a third of their triangulated points more than
#: 1 mm off; at 0.25 twice the recall for a little more (``benchmarks/README.md``, stop 67).
_EDGE_SHARE = 0.15
#: Half-height of the first window read around a peak (rows); wider stripes are read again
#: within the full window (from ``max_width_px``).
_H_SMALL = 8
#: A profile's top (:attr:`StripePoints.skew_px`): the pixels around its brightest within
#: this fraction of the peak height (a saturated or broad top's middle).
_TOP_FRACTION = 0.05
#: In a line, a candidate on a long curve this many times the other's height wins even
#: where the other lies on a stronger (summed height) curve.
_DOMINANT = 2.0
#: Both other channels falling by more than this (in the image's units) is no laser
#: light: the candidate's height is zero.
_FALL = 0.0


@njit
def _lum(img, r, c, nch):  # noqa: ANN001, ANN202 - numba kernel
    """Lightness (eq. 19) of pixel (r, c) of an (H, W, 1|3) image, float32."""
    if nch == 1:
        return np.float32(img[r, c, 0])
    a = img[r, c, 0]
    b = img[r, c, 1]
    d = img[r, c, 2]
    hi = a if a > b else b
    hi = hi if hi > d else d
    lo = a if a < b else b
    lo = lo if lo < d else d
    return np.float32(0.5) * (np.float32(hi) + np.float32(lo))


@njit
def _rgb_row(flat, r, buf):  # noqa: ANN001, ANN202
    """Lightness (eq. 19) of row r of the (H, 3 W) view of an RGB image into buf."""
    for c in range(buf.size):
        a = flat[r, 3 * c]
        b = flat[r, 3 * c + 1]
        d = flat[r, 3 * c + 2]
        hi = a if a > b else b
        hi = hi if hi > d else d
        lo = a if a < b else b
        lo = lo if lo < d else d
        buf[c] = np.float32(0.5) * (np.float32(hi) + np.float32(lo))


@njit
def _peaks_update(row, r, cmax, carg, cmin):  # noqa: ANN001, ANN202
    """Running per-column maximum (first row of it) and minimum, branch-free so that
    the loop vectorises."""
    for c in range(row.size):
        x = row[c]
        m = x > cmax[c]
        cmax[c] = x if m else cmax[c]
        carg[c] = r if m else carg[c]
        cmin[c] = x if x < cmin[c] else cmin[c]


@njit
def _row_extrema(row):  # noqa: ANN001, ANN202
    mx = row[0]
    mn = row[0]
    for c in range(1, row.size):
        x = row[c]
        mx = x if x > mx else mx
        mn = x if x < mn else mn
    return np.float32(mx), np.float32(mn)


@njit(**_JIT)
def _peaks_mono(a, want_rows):  # noqa: ANN001, ANN202
    """Pass 1 on a mono (H, W) image, on its own values (integer compares vectorise best):
    per column the brightest value and its first row, the darkest value; with
    ``want_rows`` per row the brightest and darkest values."""
    h, w = a.shape
    cmax = a[0].copy()
    cmin = a[0].copy()
    carg = np.zeros(w, np.int32)
    nr = h if want_rows else 0
    rmax = np.zeros(nr, np.float32)
    rmin = np.zeros(nr, np.float32)
    for r in range(h):
        row = a[r]
        _peaks_update(row, r, cmax, carg, cmin)
        if want_rows:
            rmax[r], rmin[r] = _row_extrema(row)
    return cmax.astype(np.float32), carg, cmin.astype(np.float32), rmax, rmin


@njit(**_JIT)
def _peaks_rgb(img, want_rows):  # noqa: ANN001, ANN202
    """Pass 1 on an (H, W, 3) image: as :func:`_peaks_mono` on the lightness."""
    h, w = img.shape[0], img.shape[1]
    flat = img.reshape(h, 3 * w)
    buf = np.zeros(w, np.float32)
    _rgb_row(flat, 0, buf)
    cmax = buf.copy()
    cmin = buf.copy()
    carg = np.zeros(w, np.int32)
    nr = h if want_rows else 0
    rmax = np.zeros(nr, np.float32)
    rmin = np.zeros(nr, np.float32)
    for r in range(h):
        _rgb_row(flat, r, buf)
        _peaks_update(buf, r, cmax, carg, cmin)
        if want_rows:
            rmax[r], rmin[r] = _row_extrema(buf)
    return cmax, carg, cmin, rmax, rmin


@njit
def _band_update(row, r, lo, hi, n_above, n_band, bmax, barg):  # noqa: ANN001, ANN202
    for c in range(row.size):
        x = np.float32(row[c])
        above = x >= lo[c]
        inb = above & (x <= hi[c])
        n_above[c] += above
        n_band[c] += inb
        m = inb & (x > bmax[c])
        bmax[c] = x if m else bmax[c]
        barg[c] = r if m else barg[c]


@njit(**_JIT)
def _scan_band(img, nch, lo, hi, active, rows):  # noqa: ANN001, ANN202
    """Pass 2: per column the number of pixels with L >= lo, of band pixels
    (lo <= L <= hi) and the brightest band pixel's row (-1: none); only for
    ``active`` columns (the others get lo = +inf) and only over ``rows`` (the rows
    that can hold a pixel >= lo: the others are skipped)."""
    h, w = img.shape[0], img.shape[1]
    flat = img.reshape(h, w * nch)
    lo_ = np.where(active, lo, np.float32(np.inf)).astype(np.float32)
    n_above = np.zeros(w, np.int32)
    n_band = np.zeros(w, np.int32)
    bmax = np.full(w, -np.inf, np.float32)
    barg = np.full(w, -1, np.int32)
    if nch == 1:
        for r in rows:
            _band_update(flat[r], r, lo_, hi, n_above, n_band, bmax, barg)
    else:
        buf = np.zeros(w, np.float32)
        for r in rows:
            _rgb_row(flat, r, buf)
            _band_update(buf, r, lo_, hi, n_above, n_band, bmax, barg)
    return n_above, n_band, barg


@njit(**_JIT)
def _noise_sigma(img, nch):  # noqa: ANN001, ANN202
    """The frame's noise sigma: the MAD of the differences between vertically
    neighbouring pixels (Donoho's robust estimator) on about 4 096 pairs spread evenly
    over the image (64 rows, 64 columns)."""
    h, w = img.shape[0], img.shape[1]
    if h < 2 or w == 0:
        return 0.0
    rows, cols = _noise_grid(h, w)
    d = np.zeros(rows.size * cols.size, np.float32)
    k = 0
    for r in rows:
        for c in cols:
            d[k] = abs(_lum(img, r + 1, c, nch) - _lum(img, r, c, nch))
            k += 1
    return _mad_sigma(d)


@njit
def _noise_grid(h, w):  # noqa: ANN001, ANN202
    """The rows and columns of the noise estimate's samples: up to 64 of each, spread
    evenly over an (h, w) image (each row with the one below it)."""
    n_r = min(h - 1, 64)
    n_c = min(w, 64)
    rows = np.empty(n_r, np.int64)
    cols = np.empty(n_c, np.int64)
    for i in range(n_r):
        rows[i] = int((h - 1) * (i + 0.5) / n_r)
    for j in range(n_c):
        cols[j] = int(w * (j + 0.5) / n_c)
    return rows, cols


@njit
def _mad_sigma(d):  # noqa: ANN001, ANN202
    """A Gaussian's sigma from absolute differences of neighbouring samples (their MAD,
    1.4826 per sigma, over sqrt(2) for a difference of two)."""
    return 1.4826 * float(np.median(d)) / np.sqrt(2.0)


@njit(**_JIT)
def _local_reference(cmax, good, half):  # noqa: ANN001, ANN202
    """min(peak, median of the good lines' peaks within +-half lines) for good lines;
    the peak itself elsewhere. A sorted sliding window: O(half) per line."""
    w = cmax.size
    out = cmax.copy()
    win = np.zeros(2 * half + 2, np.float32)
    n = 0
    for j in range(-half, w):
        add = j + half  # the line entering the window of line j
        if add < w and good[add]:
            x = cmax[add]
            i = n
            while i > 0 and win[i - 1] > x:
                win[i] = win[i - 1]
                i -= 1
            win[i] = x
            n += 1
        rem = j - half - 1  # the line leaving it
        if rem >= 0 and good[rem]:
            x = cmax[rem]
            i = 0
            while win[i] != x:
                i += 1
            for k in range(i, n - 1):
                win[k] = win[k + 1]
            n -= 1
        if j >= 0 and good[j]:
            if n % 2 == 1:
                med = win[n // 2]
            else:
                med = np.float32(0.5) * (win[n // 2 - 1] + win[n // 2])
            out[j] = min(cmax[j], med)
    return out


#: The ridge's baseline (:func:`_side_background`): beyond the stripe's foot, a fall of the
#: profile's running mean below the foot by more than this fraction of the peak's height
#: is an edge of the surface, not the stripe's flank.
_FOOT_FLAT = 0.05


@njit
def _side_background(y, valid, hw, d, lowest, k_lowest, floor, ceiling):  # noqa: ANN001, ANN202
    """The background of one side (``d`` = -1 left, +1 right) of a profile ``y`` peaking at
    ``hw``: (value, index) of the minimum of its 3-pixel running mean, walking outward,
    up to the first mean that falls below that minimum by more than ``_FOOT_FLAT`` of
    the peak's height above ``floor`` (the lower side's minimum over the window), and at
    least twice as fast as the step before, once the foot is reached (a mean at most
    halfway down to ``ceiling``, the higher side's minimum, whose next one outward falls
    by less than that fraction). Without such a fall, ``(lowest, k_lowest)``: that
    side's minimum over the window, as before."""
    m = 2 * hw + 1  # the window (y and valid may be longer: a wider one before)
    half = 0.5 * (y[hw] + ceiling)
    flat = _FOOT_FLAT * (y[hw] - floor)
    best = np.inf
    kb = k_lowest
    reached = False
    prev = np.inf
    fall = 0.0
    c = hw + 2 * d  # centre of the first mean wholly on this side
    while 1 <= c <= m - 2 and valid[c - 1] and valid[c + 1]:
        v3 = (y[c - 1] + y[c] + y[c + 1]) / 3.0
        # an edge: a new low by more than flat, falling at least twice as fast as the
        # step before (a stripe's flank or a lit face's shoulder falls ever slower)
        if reached and v3 < best - flat and prev - v3 > 2.0 * fall:
            return best, kb
        if prev != np.inf:
            fall = max(prev - v3, 0.0)
        prev = v3
        if v3 < best:
            best = v3
            kb = c
        if not reached and v3 <= half:
            cn = c + d
            reached = (cn < 1 or cn > m - 2 or not valid[cn - 1] or not valid[cn + 1]
                       or v3 - (y[cn - 1] + y[cn] + y[cn + 1]) / 3.0 < flat)
        c += d
    return lowest, k_lowest


@njit
def _profile_at(img, nch, c, p, hw, y, valid, tail_fraction, noise_t, min_peak,
                gaussian, linear=False):  # noqa: ANN001, ANN202
    """The stripe's profile in column c within +-hw rows of its brightest pixel p:
    (status, sub-pixel offset from p, peak height, FWHM, whether the window was too
    small to hold the run or the half-maximum crossings, the middle of the profile's top
    from p: the contiguous pixels around p within :data:`_TOP_FRACTION` of the peak
    height). With ``linear`` the local background is the line through the minima of the
    3-pixel running mean on either side of p (a baseline that follows a gradient), else
    the window's minimum."""
    nrow = img.shape[0]
    m = 2 * hw + 1
    for k in range(m):
        r = p - hw + k
        valid[k] = (r >= 0) and (r < nrow)
        y[k] = _lum(img, r, c, nch) if valid[k] else 0.0
    # local background: the minimum of the 3-pixel running mean in the window
    bg = np.inf
    bl = np.inf
    br = np.inf
    kl = 0
    kr = 0
    for k in range(m - 2):
        if valid[k] and valid[k + 2]:
            v3 = (y[k] + y[k + 1] + y[k + 2]) / 3.0
            bg = v3 if v3 < bg else bg
            if k + 2 < hw and v3 < bl:
                bl = v3
                kl = k + 1
            if k > hw and v3 < br:
                br = v3
                kr = k + 1
    if bg == np.inf:  # fewer than three pixels in the image
        for k in range(m):
            if valid[k] and y[k] < bg:
                bg = y[k]
    if linear:  # each side's minimum only up to an edge beyond the stripe's foot
        floor = min(bl, br)
        ceiling = max(bl, br) if max(bl, br) != np.inf else floor
        if bl != np.inf:
            bl, kl = _side_background(y, valid, hw, -1, bl, kl, floor, ceiling)
        if br != np.inf:
            br, kr = _side_background(y, valid, hw, 1, br, kr, floor, ceiling)
    if linear and bl != np.inf and br != np.inf:
        slope = (br - bl) / (kr - kl)
        for k in range(m):
            y[k] -= bl + slope * (k - kl)
    elif linear and bl != np.inf:
        for k in range(m):
            y[k] -= bl
    elif linear and br != np.inf:
        for k in range(m):
            y[k] -= br
    else:
        for k in range(m):
            y[k] -= bg
    amp = y[hw]
    t = max(tail_fraction * amp, noise_t)
    if not (amp >= min_peak and amp - t > 0):
        return _TOO_WEAK, 0.0, amp, 0.0, False, 0.0
    # the top: a flat (saturated) or broad top's middle, where a symmetric stripe's
    # centre lies whichever of its pixels is brightest
    tt = amp - _TOP_FRACTION * amp
    tr = 0
    while tr < hw and valid[hw + 1 + tr] and y[hw + 1 + tr] >= tt:
        tr += 1
    tl = 0
    while tl < hw and valid[hw - 1 - tl] and y[hw - 1 - tl] >= tt:
        tl += 1
    top = 0.5 * (tr - tl)
    # the contiguous run around p where y > t
    nr = 0
    while nr < hw and valid[hw + 1 + nr] and y[hw + 1 + nr] > t:
        nr += 1
    nl = 0
    while nl < hw and valid[hw - 1 - nl] and y[hw - 1 - nl] > t:
        nl += 1
    cut = (nr < hw and not valid[hw + 1 + nr]) or (nl < hw and not valid[hw - 1 - nl])
    filled = nr >= hw or nl >= hw
    sw = 0.0
    swk = 0.0
    for k in range(-nl, nr + 1):
        wk = y[hw + k] - t
        sw += wk
        swk += wk * k
    offset = swk / sw
    if gaussian and nl + nr + 1 >= 3:
        # weighted least-squares parabola through ln y, weights y^2 (Guo 2011)
        m0 = m1 = m2 = m3 = m4 = 0.0
        r0 = r1 = r2 = 0.0
        for k in range(-nl, nr + 1):
            yk = y[hw + k]
            g = yk * yk
            lk = np.log(yk)
            kf = float(k)
            m0 += g
            m1 += g * kf
            m2 += g * kf * kf
            m3 += g * kf * kf * kf
            m4 += g * kf * kf * kf * kf
            r0 += g * lk
            r1 += g * lk * kf
            r2 += g * lk * kf * kf
        det = m0 * (m2 * m4 - m3 * m3) - m1 * (m1 * m4 - m3 * m2) + m2 * (m1 * m3 - m2 * m2)
        if abs(det) > 1e-12 * abs(m0) ** 3:
            b1 = (m0 * (r1 * m4 - m3 * r2) - r0 * (m1 * m4 - m3 * m2)
                  + m2 * (m1 * r2 - r1 * m2)) / det
            c2 = (m0 * (m2 * r2 - r1 * m3) - m1 * (m1 * r2 - r1 * m2)
                  + r0 * (m1 * m3 - m2 * m2)) / det
            if c2 < 0:
                og = -b1 / (2.0 * c2)
                if abs(og) <= 1.5:
                    offset = og
    # full width at half maximum, linearly interpolated at both crossings
    half = amp / 2.0
    width = 0.0
    # the window must hold the run and 3 background pixels beyond it on each side (else
    # its background is the stripe's own flank), and both half-maximum crossings
    short = nr > hw - 3 or nl > hw - 3
    for direction in (-1, 1):
        mm = 0
        while (mm < hw and valid[hw + direction * (mm + 1)]
               and y[hw + direction * (mm + 1)] >= half):
            mm += 1
        frac = 0.5
        if mm < hw and valid[hw + direction * (mm + 1)]:
            inside = y[hw + direction * mm]
            outside = y[hw + direction * (mm + 1)]
            if inside != outside:
                frac = min(1.0, max(0.0, (inside - half) / (inside - outside)))
        else:
            short = short or mm >= hw
        width += mm + frac
    if filled:
        return _TOO_WIDE, offset, amp, width, short, top
    if cut:
        return _AT_BORDER, offset, amp, width, short, top
    return _OK, offset, amp, width, short, top


@njit(**_JIT)
def _centres(img, nch, good, carg, lo, hi, n_above, n_band, barg, h, h_small, tail_fraction,
             noise_t, min_peak, max_width, gaussian):  # noqa: ANN001, ANN202
    """Per column: classify the line (status), then the sub-pixel centre (row), the
    peak height above the local background and the FWHM of the stripe. The profile is
    read within +-h_small rows of the peak, and again within +-h when that window is
    too small for the stripe (wide stripes only)."""
    nrow, w = img.shape[0], img.shape[1]
    status = np.full(w, _TOO_WEAK, np.int8)
    centre = np.zeros(w, np.float64)
    amp_out = np.zeros(w, np.float64)
    width_out = np.zeros(w, np.float64)
    top_out = np.zeros(w, np.float64)
    y = np.zeros(2 * h + 1, np.float64)
    valid = np.zeros(2 * h + 1, np.bool_)
    hs = min(h, h_small)
    for c in range(w):
        if not good[c]:
            continue  # _TOO_WEAK: the line's peak is below min_peak over its darkest
        if n_above[c] == 0:
            status[c] = _NO_BAND
            continue
        lo_c = lo[c]
        hi_c = hi[c]
        p0 = barg[c] if n_band[c] > 0 else carg[c]
        # the blob (run of L >= lo) around p0, at most h pixels to each side
        p = p0
        pv = _lum(img, p0, c, nch)
        blen = 1
        bband = 1 if pv <= hi_c else 0
        wide = False
        for direction in (-1, 1):
            k = 1
            while True:
                r = p0 + direction * k
                if r < 0 or r >= nrow:
                    break
                x = _lum(img, r, c, nch)
                if x < lo_c:
                    break
                blen += 1
                if x <= hi_c:
                    bband += 1
                if x > pv:
                    pv = x
                    p = r
                k += 1
                if k > h:
                    wide = True
                    break
        if wide:
            status[c] = _TOO_WIDE
            continue
        if bband > 0:
            two = n_band[c] - bband > 0  # another blob with band pixels
        else:
            two = n_above[c] - blen > 0  # bright-only blobs, more than one
        if two:
            status[c] = _TWO_BLOBS
            continue
        st, offset, amp, width, short, top = _profile_at(img, nch, c, p, hs, y, valid,
                                                    tail_fraction, noise_t, min_peak,
                                                    gaussian)
        if short and hs < h:
            st, offset, amp, width, short, top = _profile_at(img, nch, c, p, h, y, valid,
                                                        tail_fraction, noise_t, min_peak,
                                                        gaussian)
        if st == _OK and width > max_width:
            st = _TOO_WIDE
        status[c] = st
        if st == _OK:
            centre[c] = p + offset
            amp_out[c] = amp
            width_out[c] = width
            top_out[c] = p + top
    return status, centre, amp_out, width_out, top_out


# ---------------------------------------------------------------------------- ridge kernels
#: Contrast images of the ridge detector, by index: a channel's excess over the other two
#: (a red, green or blue laser) and the seed's lightness (eq. 19; mono images, white lasers).
CONTRASTS: tuple[str, ...] = ("red", "green", "blue", "lightness")
_LIGHTNESS = 3
#: Not a detection contrast: the luma (Rec. 601, what JPEG stores at full resolution),
#: the profile of the sub-pixel centre with ``centre_on="luma"``.
_LUMA = 4
#: Offsets (pixels) of the two-sided ridge test, and the lines linked across a gap.
_RIDGE_A1, _RIDGE_A2, _LINK_GAP = 3, 6, 3
#: Heights examined together by the scans' candidate updates (skipped when none counts).
_BLOCK = 32
#: The lightness is chosen over the best laser colour when its ridge is this much more
#: consistent.
_LIGHTNESS_PREFERRED = 8.0


@njit
def _contrast_px(img, r, c, k, nch):  # noqa: ANN001, ANN202
    """Contrast ``k`` (index in CONTRASTS) of pixel (r, c) and the pixel's largest other
    channel (0 for the lightness), float32, in the image's units."""
    if nch == 1:
        return np.float32(img[r, c, 0]), np.float32(0.0)
    a = np.float32(img[r, c, 0])
    b = np.float32(img[r, c, 1])
    d = np.float32(img[r, c, 2])
    if k == 0:
        m = max(b, d)
        return a - m, m
    if k == 1:
        m = max(a, d)
        return b - m, m
    if k == 2:
        m = max(a, b)
        return d - m, m
    return np.float32(0.5) * (max(max(a, b), d) + min(min(a, b), d)), np.float32(0.0)


def _saturation(dtype: np.dtype) -> float:
    """The level from which a channel counts as saturated (98 % of the full scale; 250
    for uint8)."""
    return 250.0 if dtype == np.uint8 else 0.98 * _full_scale(dtype)


def _probe(img: np.ndarray, k: int, step: int, thr: float,
           spans: tuple[np.ndarray, ...]) -> tuple[float, float]:
    """How strongly contrast k shows one stripe crossing the rows, and the columns: on
    every ``step``-th row (column), the two strongest ridges, linked into curves as
    :func:`_link` does for the lines (a step of at most ``step`` + 2 px between sampled
    lines: the stripe within 45 degrees of the lines' normal); the score is the summed
    height of the strongest curve over 3 sampled lines or more (0 for none), so that
    clutter, short and scattered, scores little and a long stripe much. Only the lines'
    ``spans`` (:func:`_spans`: the region of interest) are searched."""
    sat = np.float32(_saturation(img.dtype))
    sep = _RIDGE_A2 + 1
    clo, chi, rlo, rhi = spans
    out = []
    if _fast8(img, k):
        s_rows, s_cols = _probe8(img, k, step, float(thr), clo, chi, rlo, rhi)
        return float(s_rows), float(s_cols)
    for along_u in (True, False):
        lo, hi = (rlo, rhi) if along_u else (clo, chi)
        m1, p1, m2, p2 = _probe_image(img, k, step, _RIDGE_A1, _RIDGE_A2,
                                      np.float32(thr), sep, sat, along_u, lo, hi)
        *_, strong = _link(m1, p1, m2, p2, sep, float(step + 2), 1, 3, False)
        out.append(float(strong.max()) if strong.size else 0.0)
    return out[0], out[1]


@njit
def _heights(x, y0, yu1, yd1, yu2, yd2, n):  # noqa: ANN001, ANN202
    """x = y0 - min(max(yu1, yd1), max(yu2, yd2)): the two-sided ridge height."""
    for c in range(n):
        x[c] = y0[c] - min(max(yu1[c], yd1[c]), max(yu2[c], yd2[c]))


@njit
def _channel_row(flat, r, k, nch, two, c0):  # noqa: ANN001, ANN202
    """Row r of the (H, W * nch) view of an image into c0, for contrast k, in one
    vectorisable loop: the laser's channel, or the lightness (a mono image: its values;
    twice the lightness when ``two``: uint8 RGB into int16, exact)."""
    w = c0.size
    if nch == 1:
        for c in range(w):
            c0[c] = flat[r, c]
        return
    f = flat[r]
    if k == _LIGHTNESS:
        for c in range(w):
            a = c0.dtype.type(f[3 * c])
            b = c0.dtype.type(f[3 * c + 1])
            d = c0.dtype.type(f[3 * c + 2])
            s = max(max(a, b), d) + min(min(a, b), d)
            c0[c] = s if two else s / 2
        return
    for c in range(w):
        c0[c] = f[3 * c + k]


@njit
def _rise_at(img, r, c, ch, a1, a2, along_u):  # noqa: ANN001, ANN202
    """Two-sided ridge height of channel ch at (r, c), across the line (along u or v)."""
    if along_u:
        y0 = np.float32(img[r, c, ch])
        b1 = max(np.float32(img[r, c - a1, ch]), np.float32(img[r, c + a1, ch]))
        b2 = max(np.float32(img[r, c - a2, ch]), np.float32(img[r, c + a2, ch]))
    else:
        y0 = np.float32(img[r, c, ch])
        b1 = max(np.float32(img[r - a1, c, ch]), np.float32(img[r + a1, c, ch]))
        b2 = max(np.float32(img[r - a2, c, ch]), np.float32(img[r + a2, c, ch]))
    return y0 - min(b1, b2)


@njit
def _luma_rise_at(img, r, c, a1, a2, along_u):  # noqa: ANN001, ANN202
    """Two-sided ridge height of the Rec. 601 luma (:func:`_contrast_at`'s ``_LUMA``, a
    JPEG's full-resolution component) of RGB pixel (r, c), across the line (as
    :func:`_rise_at`), float32."""
    return _luma_rise_step_at(img, r, c, a1, a2, along_u)[0]


@njit
def _luma_rise_step_at(img, r, c, a1, a2, along_u):  # noqa: ANN001, ANN202
    """The luma's two-sided rise at (r, c) (:func:`_luma_rise_at`) and its larger step
    across it between the pixels a1 and a2 away on either side (an edge's contrast, as
    :func:`_step_at`), from one read of the five pixels, float32."""
    y0 = _contrast_at(img, r, c, _LUMA, 3, False)
    if along_u:
        m1 = _contrast_at(img, r, c - a1, _LUMA, 3, False)
        p1 = _contrast_at(img, r, c + a1, _LUMA, 3, False)
        m2 = _contrast_at(img, r, c - a2, _LUMA, 3, False)
        p2 = _contrast_at(img, r, c + a2, _LUMA, 3, False)
    else:
        m1 = _contrast_at(img, r - a1, c, _LUMA, 3, False)
        p1 = _contrast_at(img, r + a1, c, _LUMA, 3, False)
        m2 = _contrast_at(img, r - a2, c, _LUMA, 3, False)
        p2 = _contrast_at(img, r + a2, c, _LUMA, 3, False)
    rise = np.float32(y0 - min(max(m1, p1), max(m2, p2)))
    return rise, np.float32(max(abs(m1 - p1), abs(m2 - p2)))


@njit
def _laser_at(img, r, c, k, a1, a2, along_u, xk, sat, floor):  # noqa: ANN001, ANN202
    """The laser's height at (r, c) from its channel's rise xk: ``min(xk, xk - max(rise
    of the other two channels))`` (a laser adds light, mostly of its colour: its channel
    rises, and more than the others; a thin white thing rises in all three, a grey joint
    between red tiles more in blue than in green, a green cable on a white wall falls in
    all three). Where the laser's channel is saturated (>= sat) its rise is clipped
    while the others still rise: there it must rise more than half of theirs. Where
    both others fall (an edge's ringing, a dark rim: a laser raises every channel a
    little), zero; where one falls, its fall is taken off (a laser only adds light: a
    channel that falls is the surface's colour changing). And at most the luma's
    two-sided rise over :data:`_LUMA_SHARE`: a laser's light raises the luma too, while
    a JPEG's chroma, stored at half resolution and smeared onto the bright side of a
    colour edge, makes a ridge of one channel without a luma ridge; zero where the
    luma's rise is less than :data:`_EDGE_SHARE` of its step across the pixel (that
    ringing, with the luma's own small overshoot beside the edge). A height not above
    ``floor`` (the line's second candidate, which the caller keeps it only above) is
    returned without the luma's cap."""
    i1 = 1 if k == 0 else 0
    i2 = 1 if k == 2 else 2
    r1 = _rise_at(img, r, c, i1, a1, a2, along_u)
    r2 = _rise_at(img, r, c, i2, a1, a2, along_u)
    m = max(r1, r2)
    if np.float32(img[r, c, k]) >= sat:
        m = np.float32(0.5) * m
    x = np.float32(xk)
    if m < -np.float32(_FALL):  # both other channels fall: an edge's ringing, not light
        return np.float32(0.0)
    f = min(r1, r2)
    # one falls: the surface's colour changes; a laser only adds
    h = min(x, x - m) + f if f < np.float32(0.0) else min(x, x - m)
    if not h > floor:  # the caller's candidate to beat: rejected in any case
        return h
    # and its luma rises too (a JPEG's chroma fringe at a colour edge does not)
    lr, step = _luma_rise_step_at(img, r, c, a1, a2, along_u)
    # not a JPEG's ringing on the bright side of an edge (a small overshoot of the luma
    # beside a step many times its height, with a chroma fringe in the laser's channel)
    if lr < np.float32(_EDGE_SHARE) * step:
        return np.float32(0.0)
    return min(h, lr / np.float32(_LUMA_SHARE))


@njit
def _outside(x, i0, i1, low):  # noqa: ANN001, ANN202
    """x[i] = low outside i0 <= i <= i1 (the region of interest of one line)."""
    n = x.size
    for i in range(0, min(max(i0, 0), n)):
        x[i] = low
    for i in range(max(i1 + 1, 0), n):
        x[i] = low


@njit(**_JIT)
def _roi_spans(mask):  # noqa: ANN001, ANN202
    """Per column the first and last row of a (H, W) bool region, and per row the first
    and last column, in one pass (an empty line: first = size, last = -1). The row's
    first and last are min/max reductions in the same branch-free loop (searching them
    pixel by pixel cost 0.6-0.9 ms at 1280 x 960; now 0.07)."""
    h, w = mask.shape
    clo = np.full(w, h, np.int32)
    chi = np.full(w, -1, np.int32)
    rlo = np.full(h, w, np.int32)
    rhi = np.full(h, -1, np.int32)
    none_r, none_c, out_c = np.int32(h), np.int32(w), np.int32(-1)
    for r in range(h):
        row = mask[r]
        rr = np.int32(r)
        first = none_c
        last = out_c
        for c in range(w):  # branch-free: vectorises
            on = row[c]
            cc = np.int32(c)
            clo[c] = min(clo[c], rr if on else none_r)
            chi[c] = rr if on else chi[c]
            first = min(first, cc if on else none_c)
            last = max(last, cc if on else out_c)
        rlo[r] = first
        rhi[r] = last
    return clo, chi, rlo, rhi


@njit(**_JIT)
def _ridge_scan_cols(img, k, two, ring, a1, a2, sep, thr, sat, lo, hi):  # noqa: ANN001, ANN202
    """Per column (profiles along the rows) the two strongest ridges of contrast k
    above ``thr``, at least ``sep`` rows apart: heights and rows (-10**6: none).

    The ridge height of a channel, ``x = y(r) - min(max(y(r -+ a1)), max(y(r -+ a2)))``,
    is a peak against the local baseline on both sides at one of two distances (zero on
    a step edge or a gradient). For a laser colour, where the laser channel's height
    could count (beats a column's second candidate), it is lowered by the other
    channels' rise (:func:`_laser_at`); for the lightness it is ``x`` of the lightness.
    One pass over the image: each row's channel is read once into a ring of ``2 a2 + 1``
    rows (``ring``), the heights of a row in one vectorised loop, and a column's
    candidates are updated only where a height beats its second (rare once the
    threshold holds them). Only rows ``lo[c] <= r <= hi[c]`` of column c are candidates
    (the region of interest)."""
    h, w = img.shape[0], img.shape[1]
    nch = img.shape[2]
    flat = img.reshape(h, w * nch)
    laser = nch == 3 and k != _LIGHTNESS
    nr = 2 * a2 + 1
    m1 = np.full(w, thr, ring.dtype)
    m2 = np.full(w, thr, ring.dtype)
    p1 = np.full(w, -(10 ** 6), np.int32)
    p2 = np.full(w, -(10 ** 6), np.int32)
    x = np.zeros(w, ring.dtype)
    for r in range(h):
        _channel_row(flat, r, k, nch, two, ring[r % nr])
        rc = r - a2
        if rc < a2:
            continue
        _heights(x, ring[rc % nr], ring[(rc - a1) % nr], ring[(rc + a1) % nr],
                 ring[(rc - a2) % nr], ring[(rc + a2) % nr], w)
        for c in range(w):  # outside the region: no candidate (a vectorised select)
            x[c] = x[c] if (rc >= lo[c]) & (rc <= hi[c]) else thr
        for b in range(0, w, _BLOCK):
            # whether any height of the block beats its column's second (vectorised)
            e = min(b + _BLOCK, w)
            anyb = False
            for c in range(b, e):
                anyb |= x[c] > m2[c]
            if not anyb:
                continue
            for c in range(b, e):
                xc = x[c]
                if not xc > m2[c]:
                    continue
                if laser:
                    xc = _laser_at(img, rc, c, k, a1, a2, False, xc, sat, m2[c])
                    if not xc > m2[c]:
                        continue
                m1[c], p1[c], m2[c], p2[c] = _keep_two(xc, rc, m1[c], p1[c], m2[c], p2[c], sep)
    return m1, p1, m2, p2


@njit(**_JIT)
def _ridge_scan_rows(img, k, two, rowbuf, a1, a2, sep, thr, sat, lo, hi):  # noqa: ANN001, ANN202
    """As :func:`_ridge_scan_cols`, per row (profiles along the columns): each row's
    channel read into ``rowbuf`` ((W,)), its heights computed in one vectorised loop,
    then its two strongest ridges found, among columns ``lo[r] <= c <= hi[r]``."""
    h, w = img.shape[0], img.shape[1]
    nch = img.shape[2]
    flat = img.reshape(h, w * nch)
    laser = nch == 3 and k != _LIGHTNESS
    m1 = np.full(h, thr, rowbuf.dtype)
    m2 = np.full(h, thr, rowbuf.dtype)
    p1 = np.full(h, -(10 ** 6), np.int32)
    p2 = np.full(h, -(10 ** 6), np.int32)
    n = max(w - 2 * a2, 0)
    x = np.zeros(n, rowbuf.dtype)
    # shifted views of the row buffer: loops over distinct arrays vectorise, indexing
    # one array at run-time offsets does not
    b0 = rowbuf
    s0, su1, sd1, su2, sd2 = a2, a2 - a1, a2 + a1, 0, 2 * a2
    for r in range(h):
        _channel_row(flat, r, k, nch, two, b0)
        _heights(x, b0[s0:s0 + n], b0[su1:su1 + n], b0[sd1:sd1 + n], b0[su2:su2 + n],
                 b0[sd2:sd2 + n], n)
        _outside(x, lo[r] - a2, hi[r] - a2, thr)
        v1 = thr
        v2 = thr
        c1 = -(10 ** 6)
        c2 = -(10 ** 6)
        for b in range(0, n, _BLOCK):
            # a block's maximum (a vectorised reduction) decides whether to look inside:
            # after the first candidates, almost no block holds a height above the second
            e = min(b + _BLOCK, n)
            bm = x[b]
            for i in range(b + 1, e):
                bm = max(bm, x[i])
            if not bm > v2:
                continue
            for i in range(b, e):
                xc = x[i]
                if not xc > v2:
                    continue
                c = i + a2
                if laser:
                    xc = _laser_at(img, r, c, k, a1, a2, True, xc, sat, v2)
                    if not xc > v2:
                        continue
                v1, c1, v2, c2 = _keep_two(xc, c, v1, c1, v2, c2, sep)
        m1[r] = v1
        m2[r] = v2
        p1[r] = c1
        p2[r] = c2
    return m1, p1, m2, p2


@njit
def _channel8(f, stride, ch, buf, c0, c1):  # noqa: ANN001, ANN202
    """Channel ``ch`` of pixels ``c0 <= c < c1`` of a row of interleaved uint8 pixels
    (``stride`` = 1 or 3 channels each) into ``buf``; the offsets go into the slices and
    the loops run from 0 with a literal stride, so that the loads vectorise (shuffles)."""
    n = c1 - c0
    dst = buf[c0:c1]
    if stride == 1:
        src = f[c0:c1]
        for c in range(n):
            dst[c] = src[c]
    else:
        src = f[3 * c0 + ch:3 * c1]
        for c in range(n):
            dst[c] = src[3 * c]


@njit
def _over8(xb, f0, fu1, fd1, fu2, fd2, tb, n):  # noqa: ANN001, ANN202
    """uint8 profiles: ``xb[i]`` = by how much the two-sided ridge height
    ``f0 - min(max(fu1, fd1), max(fu2, fd2))`` (clipped at 0) of pixel i beats
    ``tb[i]`` (0 where it does not), in saturating byte arithmetic (32 pixels per
    instruction); returns the largest."""
    for i in range(n):
        y0 = f0[i]
        m = min(min(max(fu1[i], fd1[i]), max(fu2[i], fd2[i])), y0)
        x = np.uint8(y0 - m)
        xb[i] = np.uint8(x - min(x, tb[i]))
    acc = np.uint8(0)
    for i in range(n):
        x = xb[i]
        acc = x if x > acc else acc
    return acc


@njit
def _nonzero8(xbuf, words, i0, i1, cj):  # noqa: ANN001, ANN202
    """The indices ``i0 <= i < i1`` of the non-zero bytes of ``xbuf`` (``words``: its
    uint64 view, read 8 bytes at a time), in order, into ``cj``; returns their number."""
    nc = 0
    for wi in range(i0 // 8, (i1 + 7) // 8):
        wv = words[wi]
        i = 8 * wi
        while wv != 0:
            if (wv & np.uint64(0xFF)) and i >= i0 and i < i1:
                cj[nc] = i
                nc += 1
            wv >>= np.uint64(8)
            i += 1
    return nc


def _fast8(img: np.ndarray, k: int) -> bool:
    """Whether the byte kernels (:func:`_lines8`, :func:`_ridge_scan_cols8`) serve
    contrast k of this kernel image: uint8, a laser colour or a mono image."""
    return img.dtype == np.uint8 and (img.shape[2] == 1 or k != _LIGHTNESS)


@njit(**_JIT)
def _lines8(img, arr, stride, k, lines, rows, a1, a2, sep, thr, sat, lo, hi,
            along_u):  # noqa: ANN001, ANN202
    """:func:`_ridge_scan_rows` (and the axis probe's lines) on a uint8 image, with the
    same results, in byte arithmetic: line ``lines[q]`` is row ``rows[q]`` of ``arr``
    (the image's rows, ``stride`` = its channels, or gathered columns of the laser's
    channel, ``stride`` = 1). Per line the laser's channel (a mono image's values) is
    read into a buffer, its heights above ``thr`` found in vectorised loops (32 pixels
    per instruction) and only the pixels where a height beats ``thr`` (8 bytes at a
    time) are offered to the line's two best ridges as :func:`_ridge_scan_rows` does
    (the laser's height :func:`_laser_at` from the image; ``along_u``: across the
    image's columns). A pixel on the best ridge that is not above it is passed over
    (it changes nothing; :func:`_laser_at` never raises a height). Only pixels
    ``lo[line] <= i <= hi[line]`` are candidates. Returns float32 heights and int32
    positions."""
    nl = lines.size
    length = arr.shape[1] // stride
    laser = img.shape[2] == 3
    ch = k if stride == 3 else 0
    nw = (length + 7) // 8
    xbuf = np.zeros(8 * nw, np.uint8)
    words = xbuf.view(np.uint64)
    buf = np.zeros(length, np.uint8)
    cj = np.zeros(length, np.int64)
    t8 = np.uint8(min(max(np.floor(thr), 0.0), 255.0))  # x > thr <=> x > floor(thr)
    tb = np.full(length, t8, np.uint8)
    thr32 = np.float32(thr)
    m1 = np.full(nl, thr32, np.float32)
    m2 = np.full(nl, thr32, np.float32)
    p1 = np.full(nl, -(10 ** 6), np.int32)
    p2 = np.full(nl, -(10 ** 6), np.int32)
    for q in range(nl):
        ln = lines[q]
        i0 = max(lo[ln], a2)
        i1 = min(hi[ln], length - 1 - a2) + 1
        if i0 >= i1:
            continue
        _channel8(arr[rows[q]], stride, ch, buf, i0 - a2, i1 + a2)  # what the heights read
        acc = _over8(xbuf[i0:i1], buf[i0:i1], buf[i0 - a1:i1 - a1], buf[i0 + a1:i1 + a1],
                     buf[i0 - a2:i1 - a2], buf[i0 + a2:i1 + a2], tb[i0:i1], i1 - i0)
        if acc == 0:
            continue
        nc = _nonzero8(xbuf, words, i0, i1, cj)
        v1 = thr32
        v2 = thr32
        c1 = -(10 ** 6)
        c2 = -(10 ** 6)
        for i in range(nc):
            c = cj[i]
            xc = np.float32(np.int32(xbuf[c]) + np.int32(t8))
            if not xc > v2:
                continue
            if abs(c - c1) <= sep and not xc > v1:
                continue
            if laser:
                if along_u:
                    xc = _laser_at(img, ln, c, k, a1, a2, True, xc, sat, v2)
                else:
                    xc = _laser_at(img, c, ln, k, a1, a2, False, xc, sat, v2)
                if not xc > v2:
                    continue
            v1, c1, v2, c2 = _keep_two(xc, c, v1, c1, v2, c2, sep)
        m1[q] = v1
        m2[q] = v2
        p1[q] = c1
        p2[q] = c2
    return m1, p1, m2, p2


@njit(**_JIT)
def _gather_cols8(img, ch, cols):  # noqa: ANN001, ANN202
    """Channel ch of the image's columns ``cols`` as (len(cols), H) uint8 rows, read
    row by row (one pass over the image instead of one per column)."""
    h = img.shape[0]
    out = np.empty((cols.size, h), np.uint8)
    for r in range(h):
        for j in range(cols.size):
            out[j, r] = img[r, cols[j], ch]
    return out


@njit(**_JIT)
def _ridge_scan_cols8(img, k, a1, a2, sep, thr, sat, lo, hi):  # noqa: ANN001, ANN202
    """:func:`_ridge_scan_cols` on a uint8 image (a laser colour or mono), with the same
    results, in byte arithmetic: each row's laser channel is read once into a ring of
    ``2 a2 + 1`` rows; per row the heights of every column beating a per-column
    threshold (its second candidate; 255 where the column's region does not hold the
    row) in vectorised loops (32 columns per instruction); only the columns where a
    height beats it (found 8 at a time) are updated as :func:`_ridge_scan_cols` does
    (a pixel on the best ridge not above it is passed over: it changes nothing). Rows
    that no column's region holds are not read."""
    h, w, nch = img.shape
    laser = nch == 3
    ch = k if laser else 0
    flat = img.reshape(h, w * nch)
    nr = 2 * a2 + 1
    ring = np.zeros((nr, w), np.uint8)
    nw = (w + 7) // 8
    xbuf = np.zeros(8 * nw, np.uint8)
    words = xbuf.view(np.uint64)
    cj = np.zeros(w, np.int64)
    tb = np.full(w, 255, np.uint8)
    m1 = np.full(w, thr, np.int16)
    m2 = np.full(w, thr, np.int16)
    p1 = np.full(w, -(10 ** 6), np.int32)
    p2 = np.full(w, -(10 ** 6), np.int32)
    # column c is searched in rows lo[c] .. hi[c]: it joins at row lo[c], leaves after hi[c]
    on = np.argsort(lo)
    off = np.argsort(hi)
    rmin = h
    rmax = -1
    for c in range(w):
        if lo[c] <= hi[c]:
            rmin = min(rmin, lo[c])
            rmax = max(rmax, hi[c])
    r0 = max(rmin, a2)
    r1 = min(rmax, h - 1 - a2)
    ion = 0
    ioff = 0
    for r in range(r0 - a2, r1 + a2 + 1):
        _channel8(flat[r], nch, ch, ring[r % nr], 0, w)
        rc = r - a2
        if rc < r0:
            continue
        while ion < w and lo[on[ion]] <= rc:
            c = on[ion]
            if hi[c] >= rc:
                tb[c] = np.uint8(min(max(np.int32(m2[c]), 0), 255))
            ion += 1
        while ioff < w and hi[off[ioff]] < rc:
            tb[off[ioff]] = 255
            ioff += 1
        acc = _over8(xbuf, ring[rc % nr], ring[(rc - a1) % nr], ring[(rc + a1) % nr],
                     ring[(rc - a2) % nr], ring[(rc + a2) % nr], tb, w)
        if acc == 0:
            continue
        nc = _nonzero8(xbuf, words, 0, w, cj)
        for i in range(nc):
            c = cj[i]
            xc = np.float32(np.int32(xbuf[c]) + np.int32(tb[c]))  # > m2[c]
            if abs(rc - p1[c]) <= sep and not xc > m1[c]:
                continue
            if laser:
                xc = _laser_at(img, rc, c, k, a1, a2, False, xc, sat, m2[c])
                if not xc > m2[c]:
                    continue
            m1[c], p1[c], m2[c], p2[c] = _keep_two(xc, rc, m1[c], p1[c], m2[c], p2[c], sep)
            tb[c] = np.uint8(min(max(np.int32(m2[c]), 0), 255))
    return m1, p1, m2, p2


@njit(**_JIT)
def _noise8(img, k):  # noqa: ANN001, ANN202
    """:func:`_noise_contrast` of a uint8 image's laser channel (a mono image's values):
    the same samples, their median from a histogram of the 256 possible differences
    (the same value as sorting them)."""
    h, w, nch = img.shape
    if h < 2 or w == 0:
        return 0.0
    ch = k if nch == 3 else 0
    n_r = min(h - 1, 64)
    n_c = min(w, 64)
    hist = np.zeros(256, np.int64)
    for i in range(n_r):
        r = int((h - 1) * (i + 0.5) / n_r)
        for j in range(n_c):
            c = int(w * (j + 0.5) / n_c)
            hist[abs(np.int32(img[r + 1, c, ch]) - np.int32(img[r, c, ch]))] += 1
    n = n_r * n_c
    r_lo, r_hi = (n - 1) // 2, n // 2  # the middle ranks (one when n is odd)
    v_lo = v_hi = -1
    cum = 0
    for v in range(256):
        cum += hist[v]
        if v_lo < 0 and cum > r_lo:
            v_lo = v
        if cum > r_hi:
            v_hi = v
            break
    return 1.4826 * ((v_lo + v_hi) / 2.0) / np.sqrt(2.0)


@njit(**_JIT)
def _probe8(img, k, step, thr, clo, chi, rlo, rhi):  # noqa: ANN001, ANN202
    """:func:`_probe` on a uint8 image for a laser colour (or a mono image), in one
    compiled call: the sampled rows read in place, the sampled columns gathered in one
    pass over the rows (:func:`_gather_cols8`), both by :func:`_lines8`."""
    h, w, nch = img.shape
    sep = _RIDGE_A2 + 1
    ch = k if nch == 3 else 0
    sat = np.float32(250.0)  # _saturation(uint8)
    thr32 = float(np.float32(thr))
    rows = np.arange(step // 2, h, step)
    m1, p1, m2, p2 = _lines8(img, img.reshape(h, w * nch), nch, k, rows, rows, _RIDGE_A1,
                             _RIDGE_A2, sep, thr32, sat, rlo, rhi, True)
    strong = _link(m1, p1, m2, p2, sep, float(step + 2), 1, 3, False)[5]
    s_rows = strong.max() if strong.size else 0.0
    cols = np.arange(step // 2, w, step)
    m1, p1, m2, p2 = _lines8(img, _gather_cols8(img, ch, cols), 1, k, cols,
                             np.arange(cols.size), _RIDGE_A1, _RIDGE_A2, sep, thr32, sat,
                             clo, chi, False)
    strong = _link(m1, p1, m2, p2, sep, float(step + 2), 1, 3, False)[5]
    s_cols = strong.max() if strong.size else 0.0
    return s_rows, s_cols


@njit(**_JIT)
def _ridge_frame8(img, k, axis_mode, step, min_peak, noise_k, link_px, min_run, h,
                  tail_fraction, max_width_px, gaussian, clo, chi, rlo, rhi, follow):  # noqa: ANN001, ANN202
    """Steps 2-5 of the ridge detector (and the axis of step 4 when ``axis_mode`` is 0;
    1: rows, 2: columns) on a uint8 image for a laser colour or a mono image, in one
    compiled call that holds no interpreter lock (frames run in parallel on threads):
    the axis probe (:func:`_probe8`), the noise and threshold, the scan
    (:func:`_lines8` or :func:`_ridge_scan_cols8`), the curves (:func:`_link`) and the
    sub-pixel centres (:func:`_ridge_centres`), exactly as :func:`_extract_ridge` calls
    them one by one for other images."""
    h_img = img.shape[0]
    rows_axis = axis_mode == 1
    if axis_mode == 0:
        s_rows, s_cols = _probe8(img, k, step, min_peak, clo, chi, rlo, rhi)
        rows_axis = s_rows > s_cols
    sigma_n = _noise8(img, k)
    thr = max(min_peak, 2.0 * noise_k * sigma_n)
    thr_w = np.int16(np.ceil(thr))
    sep = _RIDGE_A2 + 1
    sat = np.int16(250)  # _saturation(uint8)
    if rows_axis:
        lines = np.arange(h_img)
        m1f, p1, m2f, p2 = _lines8(img, img.reshape(h_img, img.shape[1] * img.shape[2]),
                                   img.shape[2], k, lines, lines, _RIDGE_A1, _RIDGE_A2, sep,
                                   float(thr_w), sat, rlo, rhi, True)
        m1 = m1f.astype(np.int16)  # as _ridge_scan_rows stores them
        m2 = m2f.astype(np.int16)
    else:
        m1, p1, m2, p2 = _ridge_scan_cols8(img, k, _RIDGE_A1, _RIDGE_A2, sep, thr_w, sat,
                                           clo, chi)
    win, status, run, n_second, n_isolated, _ = _link(m1, p1, m2, p2, sep, link_px,
                                                      _LINK_GAP, min_run, True)
    if follow:
        lo, hi = (rlo, rhi) if rows_axis else (clo, chi)
        _extend(img, k, rows_axis, win, status, run, float(thr_w), link_px, _LINK_GAP, lo,
                hi, 250.0)
    st2, centre, amp, width, top = _ridge_centres(img, k, False, rows_axis, win, h,
                                                  _H_SMALL, tail_fraction, noise_k * sigma_n,
                                                  min_peak, max_width_px, gaussian)
    return (rows_axis, sigma_n, win, status, run, n_second, n_isolated, st2, centre, amp,
            width, top)


@njit(**_JIT)
def _ridge_tail8(img, rows_axis, status, st2, lo, hi, centre, amp, width, top, run, min_run,
                 max_width_px):  # noqa: ANN001, ANN202
    """The end of :func:`_extract_ridge` for the byte kernels' frames, in one compiled
    call with numpy's arithmetic (the same values): the lines' final status and its
    counts, the centres (u, v), their peak, width, skew (the centre from its profile's
    top, :class:`StripePoints`), the width, contrast and curve terms
    of the confidence (the SNR term's exp stays with numpy), eq. 18's channel sums on
    the centres' pixels and the median slope between neighbouring lines' centres (NaN
    with fewer than 3 pairs) for :func:`_angle_deg`."""
    n = status.size
    h_img, w_img = img.shape[0], img.shape[1]
    counts = np.zeros(len(REJECTION_REASONS) + 1, np.int64)
    for i in range(n):
        st = st2[i] if status[i] == _OK else status[i]
        if st == _TOO_WEAK and lo[i] > hi[i]:
            st = _OUTSIDE
        status[i] = st
        counts[st] += 1
    ok = np.flatnonzero(status == _OK)
    m = ok.size
    amp_c = amp[ok]
    width_g = width[ok]
    c_width = np.empty(m)
    c_peak = np.empty(m)
    c_run = np.empty(m)
    med = np.median(amp_c) if m else 1.0
    med = max(med, 1e-12)
    for j in range(m):
        c_width[j] = min(max(2.0 - 2.0 * width_g[j] / max_width_px, 0.0), 1.0)
        c_peak[j] = min(max(amp_c[j] / med, 0.0), 1.0)
        c_run[j] = min(max(run[ok[j]] / (2.0 * min_run), 0.0), 1.0)
    line = ok.astype(np.int64)
    along = line.astype(np.float64)
    across = centre[ok]
    skew = across - top[ok]
    sums = np.zeros(img.shape[2])
    for j in range(m):  # eq. 18 on the centres' pixels
        a = min(max(np.rint(along[j]), 0), (h_img if rows_axis else w_img) - 1)
        b = min(max(np.rint(across[j]), 0), (w_img if rows_axis else h_img) - 1)
        r, c = (int(a), int(b)) if rows_axis else (int(b), int(a))
        for ch in range(img.shape[2]):
            sums[ch] += img[r, c, ch]
    d = np.empty(m)
    nd = 0
    for j in range(m - 1):
        if line[j + 1] - line[j] == 1:
            d[nd] = across[j + 1] - across[j]
            nd += 1
    slope = np.median(d[:nd]) if nd >= 3 else np.nan
    return (status, counts, line, across, amp_c, width_g, skew, c_width, c_peak, c_run, sums,
            slope)


@njit(**_JIT)
def _probe_image(img, k, step, a1, a2, thr, sep, sat, along_u, lo, hi):  # noqa: ANN001, ANN202
    """:func:`_ridge_scan_rows` on every ``step``-th row (``along_u``: profiles along
    u, a stripe crossing the rows) or :func:`_ridge_scan_cols` on every ``step``-th
    column, read from the image in place: the two strongest ridges of each sampled
    line ``ln`` between ``lo[ln]`` and ``hi[ln]`` (the region of interest)."""
    h, w, nch = img.shape
    laser = nch == 3 and k != _LIGHTNESS
    lines = np.arange(step // 2, h if along_u else w, step)
    m = w if along_u else h
    nl = lines.size
    m1 = np.full(nl, thr, np.float32)
    m2 = np.full(nl, thr, np.float32)
    p1 = np.full(nl, -(10 ** 6), np.int32)
    p2 = np.full(nl, -(10 ** 6), np.int32)
    y = np.zeros(m, np.float32)
    nn = max(m - 2 * a2, 0)
    x = np.zeros(nn, np.float32)
    for j in range(nl):
        ln = lines[j]
        for i in range(m):
            if along_u:
                y[i] = _contrast_at(img, ln, i, k, nch, False)
            else:
                y[i] = _contrast_at(img, i, ln, k, nch, False)
        _heights(x, y[a2:a2 + nn], y[a2 - a1:a2 - a1 + nn], y[a2 + a1:a2 + a1 + nn],
                 y[:nn], y[2 * a2:2 * a2 + nn], nn)
        _outside(x, lo[ln] - a2, hi[ln] - a2, thr)
        v1 = thr
        v2 = thr
        c1 = -(10 ** 6)
        c2 = -(10 ** 6)
        for i in range(nn):
            xc = x[i]
            if xc > v2:
                c = i + a2
                if laser:
                    if along_u:
                        xc = _laser_at(img, ln, c, k, a1, a2, True, xc, sat, v2)
                    else:
                        xc = _laser_at(img, c, ln, k, a1, a2, False, xc, sat, v2)
                    if not xc > v2:
                        continue
                v1, c1, v2, c2 = _keep_two(xc, c, v1, c1, v2, c2, sep)
        m1[j], p1[j], m2[j], p2[j] = v1, c1, v2, c2
    return m1, p1, m2, p2


@njit
def _keep_two(xc, c, v1, c1, v2, c2, sep):  # noqa: ANN001, ANN202
    """Offer candidate ``xc`` at ``c`` (already above the second best ``v2``) to a line's
    two best ridges ``(v1, c1)``, ``(v2, c2)``: within ``sep`` of the best it can only
    replace the best (one ridge); else it becomes the best or the second."""
    if abs(c - c1) <= sep:
        if xc > v1:
            v1 = xc
            c1 = c
    elif xc > v1:
        v2 = v1
        c2 = c1
        v1 = xc
        c1 = c
    else:
        v2 = xc
        c2 = c
    return v1, c1, v2, c2


@njit
def _contrast_at(img, r, c, k, nch, two):  # noqa: ANN001, ANN202
    """The profile value of pixel (r, c) for contrast k, float64: the laser's own
    channel (its rise is the stripe; where the laser saturates the channel, a flat top
    centred on the stripe, where a chroma difference would dip), or the lightness
    (twice it when ``two``, like :func:`_channel_row`)."""
    if nch == 3 and k == _LUMA:
        return (0.299 * float(img[r, c, 0]) + 0.587 * float(img[r, c, 1])
                + 0.114 * float(img[r, c, 2]))
    if nch == 3 and k != _LIGHTNESS:
        return float(img[r, c, k])
    e, _ = _contrast_px(img, r, c, k, nch)
    return 2.0 * e if two else float(e)


@njit(**_JIT)
def _noise_contrast(img, k, two):  # noqa: ANN001, ANN202
    """:func:`_noise_sigma` of contrast k (scaled like :func:`_contrast_row`)."""
    h, w, nch = img.shape
    if h < 2 or w == 0:
        return 0.0
    rows, cols = _noise_grid(h, w)
    d = np.zeros(rows.size * cols.size, np.float64)
    i_ = 0
    for r in rows:
        for c in cols:
            d[i_] = abs(_contrast_at(img, r + 1, c, k, nch, two)
                        - _contrast_at(img, r, c, k, nch, two))
            i_ += 1
    return _mad_sigma(d)


@njit(**_JIT)
def _ridge_centres(img, k, two, rows_axis, win, h, h_small, tail_fraction, noise_t,
                   min_peak, max_width, gaussian):  # noqa: ANN001, ANN202
    """Sub-pixel centres of the lines' winning ridges: the profile of contrast k across
    each line around its ridge's brightest pixel (within 2 pixels), with the linear
    local baseline (:func:`_profile_at`); statuses as :func:`_centres`."""
    nrow, ncol, nch = img.shape
    n = win.size
    length = ncol if rows_axis else nrow  # pixels along a profile
    status = np.full(n, _TOO_WEAK, np.int8)
    centre = np.zeros(n, np.float64)
    amp_out = np.zeros(n, np.float64)
    width_out = np.zeros(n, np.float64)
    top_out = np.zeros(n, np.float64)
    y = np.zeros(2 * h + 1, np.float64)
    valid = np.zeros(2 * h + 1, np.bool_)
    prof = np.zeros((2 * h + 1, 1, 1), np.float64)
    hs = min(h, h_small)
    for i in range(n):
        p0 = win[i]
        if p0 < 0:
            continue
        # the profile within +-(2 + hs) of p0 first (all that the first window reads:
        # the same values and image borders as the full one), the full +-(2 + h) only
        # when that window is too small for the stripe
        lo = max(0, p0 - 2 - hs)
        hi = min(length, p0 + 3 + hs)
        for j in range(lo, hi):
            if rows_axis:
                prof[j - lo, 0, 0] = _contrast_at(img, i, j, k, nch, two)
            else:
                prof[j - lo, 0, 0] = _contrast_at(img, j, i, k, nch, two)
        view = prof[:hi - lo]
        p = p0 - lo
        pv = view[p, 0, 0]
        for j in range(max(0, p - 2), min(hi - lo, p + 3)):
            if view[j, 0, 0] > pv:
                pv = view[j, 0, 0]
                p = j
        st, offset, amp, width, short, top = _profile_at(view, 1, 0, p, hs, y, valid,
                                                    tail_fraction, noise_t, min_peak,
                                                    gaussian, True)
        if short and hs < h:
            lo_f = max(0, p0 - 2 - h)
            hi_f = min(length, p0 + 3 + h)
            for j in range(lo_f, hi_f):
                if rows_axis:
                    prof[j - lo_f, 0, 0] = _contrast_at(img, i, j, k, nch, two)
                else:
                    prof[j - lo_f, 0, 0] = _contrast_at(img, j, i, k, nch, two)
            p += lo - lo_f
            lo = lo_f
            view = prof[:hi_f - lo_f]
            st, offset, amp, width, short, top = _profile_at(view, 1, 0, p, h, y, valid,
                                                        tail_fraction, noise_t, min_peak,
                                                        gaussian, True)
        if st == _OK and width > max_width:
            st = _TOO_WIDE
        status[i] = st
        if st == _OK:
            centre[i] = p + lo + offset
            amp_out[i] = amp
            width_out[i] = width
            top_out[i] = p + lo + top
    return status, centre, amp_out, width_out, top_out


#: Hysteresis (step 3b): the laser's height of a curve's continuation may keep only
#: this fraction of the other channels' rise (1 in the scan: :func:`_laser_at`).
_WEAK_OTHERS = 0.5
#: Hysteresis: how far (pixels per line) a continuation may leave the position its curve's
#: direction predicts.
_WEAK_TOL = 1.0
#: Hysteresis: a continuation's rise must be at least this fraction of the step across it.
_WEAK_STEP = 0.25


@njit
def _step_at(img, r, c, ch, a1, a2, along_u):  # noqa: ANN001, ANN202
    """The larger step of channel ch across (r, c) between the pixels a1 and a2 away on
    either side (an edge's contrast)."""
    if along_u:
        s1 = abs(np.float32(img[r, c - a1, ch]) - np.float32(img[r, c + a1, ch]))
        s2 = abs(np.float32(img[r, c - a2, ch]) - np.float32(img[r, c + a2, ch]))
    else:
        s1 = abs(np.float32(img[r - a1, c, ch]) - np.float32(img[r + a1, c, ch]))
        s2 = abs(np.float32(img[r - a2, c, ch]) - np.float32(img[r + a2, c, ch]))
    return max(s1, s2)


@njit
def _weak_at(img, r, c, k, a1, a2, along_u, sat, thr):  # noqa: ANN001, ANN202
    """The height of a curve's continuation at (r, c) (step 3b): the two-sided rise of
    the laser's channel (a mono image's values) less :data:`_WEAK_OTHERS` of the other
    channels' larger rise (halved where the laser's channel saturates), zero where both
    other channels fall (:func:`_laser_at` with the weaker colour test), and zero where
    it is less than :data:`_WEAK_STEP` of the channel's step across the pixel (a JPEG's
    ringing beside an edge: a small overshoot of every channel on the bright side);
    at most the luma's rise over :data:`_LUMA_SHARE`, as :func:`_laser_at`."""
    ch = 0 if img.shape[2] == 1 else k
    x = _rise_at(img, r, c, ch, a1, a2, along_u)
    if x < np.float32(_WEAK_STEP) * _step_at(img, r, c, ch, a1, a2, along_u):
        return np.float32(0.0)
    if img.shape[2] == 1:
        return x
    i1 = 1 if k == 0 else 0
    i2 = 1 if k == 2 else 2
    if (np.float32(img[r, c, k]) - max(np.float32(img[r, c, i1]), np.float32(img[r, c, i2]))
            < np.float32(thr)):  # the pixel itself not of the laser's colour: grey, white
        return np.float32(0.0)
    m = max(_rise_at(img, r, c, i1, a1, a2, along_u), _rise_at(img, r, c, i2, a1, a2, along_u))
    if np.float32(img[r, c, k]) >= sat:
        m = np.float32(0.5) * m
    if m < -np.float32(_FALL):
        return np.float32(0.0)
    return min(min(x, x - np.float32(_WEAK_OTHERS) * m),
               _luma_rise_at(img, r, c, a1, a2, along_u) / np.float32(_LUMA_SHARE))


@njit(**_JIT)
def _extend(img, k, rows_axis, win, status, run, thr, link_px, gap, lo, hi, sat):  # noqa: ANN001, ANN202
    """Step 3b, hysteresis (as Canny's and Steger's [5] line detectors): each kept curve
    is followed beyond its ends, one line at a time, to the pixel within
    :data:`_WEAK_TOL` px per line of the position its direction predicts where the
    weaker height :func:`_weak_at` is the largest and above ``thr``, until ``gap`` lines
    in a row hold none. It goes on into the lines that kept nothing (``too_weak`` or
    ``isolated``), and into a line won by another curve (its winner farther from the
    prediction) when the continuation there is higher than that winner by the same
    measure; it stops where it meets its own curve again or a rejected line. Only the
    continuation of a long curve is searched this way, so clutter elsewhere cannot
    enter: where a JPEG's half-resolution chroma leaves a thin stripe's colour mostly
    in the luma (the stripe on an object of the laser's own colour, its fading ends
    near a silhouette), the curve goes on. Updates ``win``, ``status`` (_OK) and
    ``run`` (the curve's) in place; returns the number of lines added or replaced."""
    n = win.size
    if img.shape[2] == 3 and k > 2:  # the lightness of an RGB image: not followed
        return 0
    length = img.shape[1] if rows_axis else img.shape[0]
    a1, a2 = _RIDGE_A1, _RIDGE_A2
    sat = np.float32(sat)
    ext = np.zeros(n, np.bool_)  # lines a continuation took: never taken back
    added = 0
    for d in (1, -1):
        start = 0 if d == 1 else n - 1
        stop = n if d == 1 else -1
        for i in range(start, stop, d):
            j = i + d
            if win[i] < 0 or status[i] != _OK or j < 0 or j >= n:
                continue
            if win[j] >= 0 and (ext[j] or abs(win[j] - win[i]) <= link_px):
                continue  # the curve goes on by itself
            slope = 0.0  # the curve's direction over its last (up to 4) lines
            for b in range(4, 0, -1):
                prev = i - b * d
                if 0 <= prev < n and win[prev] >= 0:
                    slope = min(max(float(win[i] - win[prev]) / b, -link_px), link_px)
                    break
            p = float(win[i])
            last = i
            while 0 <= j < n and abs(j - last) <= gap:
                g = abs(j - last)
                pred = p + slope * g
                other = win[j] >= 0
                if other and (ext[j] or abs(win[j] - pred) <= _WEAK_TOL * g + 1.0):
                    break  # its own curve again, or a line already taken
                if not other and status[j] != _TOO_WEAK and status[j] != _ISOLATED:
                    break
                best = np.float32(thr)
                if other:  # a line won by another curve: the continuation must beat it
                    if rows_axis:
                        hw = _weak_at(img, j, win[j], k, a1, a2, True, sat, thr)
                    else:
                        hw = _weak_at(img, win[j], j, k, a1, a2, False, sat, thr)
                    best = max(best, np.float32(_DOMINANT) * hw)
                c0 = max(int(np.floor(pred - _WEAK_TOL * g)), lo[j], a2)
                c1 = min(int(np.ceil(pred + _WEAK_TOL * g)), hi[j], length - 1 - a2)
                bc = -1
                for c in range(c0, c1 + 1):
                    if rows_axis:
                        x = _weak_at(img, j, c, k, a1, a2, True, sat, thr)
                    else:
                        x = _weak_at(img, c, j, k, a1, a2, False, sat, thr)
                    if x > best:
                        best = x
                        bc = c
                if bc >= 0:
                    slope = min(max(0.5 * slope + 0.5 * (bc - p) / g, -link_px), link_px)
                    p = float(bc)
                    win[j] = bc
                    status[j] = _OK
                    run[j] = run[i]
                    ext[j] = True
                    last = j
                    added += 1
                elif other:
                    break
                j += d
    return added


@njit
def _find(parent, i):  # noqa: ANN001, ANN202
    while parent[i] != i:
        parent[i] = parent[parent[i]]
        i = parent[i]
    return i


@njit(**_JIT)
def _link(m1, p1, m2, p2, sep, link_px, gap, min_run, ambiguous):  # noqa: ANN001, ANN202
    """Connect the lines' ridge candidates into curves and keep one per line.

    Candidate j of line i links to the nearest candidate of the closest earlier line
    (at most ``gap`` lines back) within ``link_px`` per line of distance. Per line, the
    candidate on the strongest curve (its candidates' summed height; then the longest)
    wins when that curve spans at least ``min_run`` lines; a curve that loses in more of
    its lines than it wins is a second line (a reflection) in all of them. With
    ``ambiguous``, a line whose two candidates lie on comparable long curves (neither
    ``_DOMINANT`` times the other's height, nearly as long and as strong) is rejected as
    ``two_blobs`` (the axis probe passes False: two parallel lines still say which way
    they run). Returns the
    winner's row (-1: none), the line's status (_OK, _TOO_WEAK: no candidate,
    _ISOLATED: only candidates on short curves, _SECOND, _TWO_BLOBS), the winner's
    curve length, the number of dropped candidates by reason (second line: on another
    long curve; isolated: on a short one), and the summed height of the winner's
    curve."""
    n = m1.size
    pos = np.zeros(2 * n, np.float64)
    val = np.zeros(2 * n, np.float64)
    ok = np.zeros(2 * n, np.bool_)
    for i in range(n):
        pos[2 * i] = p1[i]
        val[2 * i] = m1[i]
        ok[2 * i] = p1[i] >= 0
        pos[2 * i + 1] = p2[i]
        val[2 * i + 1] = m2[i]
        ok[2 * i + 1] = (p2[i] >= 0) & (abs(p2[i] - p1[i]) > sep) & ok[2 * i]
    parent = np.arange(2 * n)
    for i in range(n):
        for s in range(2):
            node = 2 * i + s
            if not ok[node]:
                continue
            best = -1
            bestd = np.inf
            for g in range(1, gap + 1):
                j = i - g
                if j < 0:
                    break
                for t in range(2):
                    nd = 2 * j + t
                    if ok[nd]:
                        d = abs(pos[node] - pos[nd])
                        if d <= link_px * g and d < bestd:
                            best = nd
                            bestd = d
                if best >= 0:
                    break
            if best >= 0:
                ra = _find(parent, node)
                rb = _find(parent, best)
                if ra != rb:
                    parent[ra] = rb
    size = np.zeros(2 * n, np.int64)
    strength = np.zeros(2 * n, np.float64)
    root = np.zeros(2 * n, np.int64)
    for node in range(2 * n):
        if ok[node]:
            root[node] = _find(parent, node)
            size[root[node]] += 1
            strength[root[node]] += val[node]
    win = np.full(n, -1, np.int64)
    status = np.full(n, _TOO_WEAK, np.int8)
    run = np.zeros(n, np.int64)
    best = np.full(n, -1, np.int64)  # winning slot per line
    won = np.zeros(2 * n, np.int64)
    lost = np.zeros(2 * n, np.int64)
    for i in range(n):
        bs = -1
        for s in range(2):
            node = 2 * i + s
            if ok[node]:
                status[i] = _ISOLATED
                rt = root[node]
                if size[rt] >= min_run:
                    if bs < 0:
                        bs = s
                    else:
                        rb = root[2 * i + bs]
                        vn, vb = val[node], val[2 * i + bs]
                        # a candidate _DOMINANT times the other's height wins (the
                        # stripe over an object's lit rim that joins it at the
                        # silhouette into a longer curve); else the stronger curve
                        # (summed height), then the longer
                        if vn > _DOMINANT * vb or (not vb > _DOMINANT * vn and (
                                strength[rt] > strength[rb] or (strength[rt] == strength[rb]
                                                                and size[rt] > size[rb]))):
                            bs = s
        best[i] = bs
        if bs >= 0:
            won[root[2 * i + bs]] += 1
            other = 2 * i + 1 - bs
            if ok[other] and size[root[other]] >= min_run:
                lost[root[other]] += 1
    # a curve that loses to another one in more of its lines than it wins is a second
    # line (a reflection beside the stripe), also where the stripe itself is missing
    n_second = 0
    n_isolated = 0
    strong = np.zeros(n, np.float64)
    for i in range(n):
        bs = best[i]
        if bs < 0:
            continue
        rt = root[2 * i + bs]
        other = 2 * i + 1 - bs
        if ok[other]:
            if size[root[other]] >= min_run:
                n_second += 1
            else:
                n_isolated += 1
        if lost[rt] > won[rt]:
            status[i] = _SECOND
            continue
        if ambiguous and ok[other] and size[root[other]] >= min_run:
            # two comparable long curves (neither _DOMINANT times the other's height,
            # nearly as long, nearly as strong on average): nothing says which one is
            # the laser's, so the line is ambiguous, as two band blobs are (seed §4.2)
            ro = root[other]
            vb, vo = val[2 * i + bs], val[other]
            if (not vb > _DOMINANT * vo and size[ro] * 10 >= size[rt] * 9
                    and strength[ro] * size[rt] * 10 >= strength[rt] * size[ro] * 8):
                status[i] = _TWO_BLOBS
                continue
        status[i] = _OK
        win[i] = int(pos[2 * i + bs])
        run[i] = size[rt]
        strong[i] = strength[rt]
    return win, status, run, n_second, n_isolated, strong


# ---------------------------------------------------------------------------- extraction
def _as_kernel_image(image: np.ndarray) -> np.ndarray:
    """(H, W, 1|3) C-contiguous, writable uint8, uint16 or float32 view/copy of an image.

    Writable: a raw frame (``mono8``, ``rgb8``: :mod:`robo3d.recording` reads it over the
    message's bytes) is read-only, and Numba types a read-only array apart from a
    writable one, so every kernel would be compiled a second time for it (36 s of the
    first frame of a monochrome cell recording after ``robo3d warm-up``); the copy costs
    0.07 ms for a 1280 x 960 mono frame, 0.3 ms in RGB."""
    if image.dtype not in (np.uint8, np.uint16, np.float32):
        image = image.astype(np.float32)
    elif not image.flags.writeable:
        image = image.copy()
    if image.ndim == 2:
        image = image.reshape(image.shape[0], image.shape[1], 1)
    return np.ascontiguousarray(image)


def _scan_peaks(img: np.ndarray, want_rows: bool) -> tuple[np.ndarray, ...]:
    """Pass 1 on an (H, W, 1|3) kernel image (see :func:`_peaks_mono`)."""
    if img.shape[2] == 1:
        return _peaks_mono(img[..., 0], want_rows)
    return _peaks_rgb(img, want_rows)


def _transpose(img: np.ndarray) -> np.ndarray:
    """The (W, H, C) transpose of an (H, W, C) kernel image, C-contiguous."""
    import cv2

    nch = img.shape[2]
    t = cv2.transpose(img if nch == 3 else img[..., 0])
    return np.ascontiguousarray(t.reshape(img.shape[1], img.shape[0], nch))


@njit(**_JIT)
def _channel_sums(img, rows, cols):  # noqa: ANN001, ANN202
    """Per channel, the sum of the pixels (rows, cols) of an (H, W, C) image, float64."""
    nch = img.shape[2]
    out = np.zeros(nch, np.float64)
    for i in range(rows.size):
        for ch in range(nch):
            out[ch] += img[rows[i], cols[i], ch]
    return out


def _eq18(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    """Eq. 18 on the pixels (rows, cols) of an (H, W, C) kernel image."""
    if np.issubdtype(img.dtype, np.integer):  # exact sums in any order: numpy's mean
        means = _channel_sums(img, rows, cols) / rows.size
    else:
        means = img[rows, cols].astype(np.float64).mean(axis=0)  # (n, C) -> (C,)
    return float((means.max() + means.min()) / 2.0)


def _check_options(o: StripeOptions) -> None:
    """``ValueError`` naming the first option of :func:`extract_stripe_centres` out of
    range."""
    if o.axis not in ("columns", "rows", "auto"):
        raise ValueError(f"axis must be 'columns', 'rows' or 'auto', got {o.axis!r}")
    if o.method not in ("cog", "gaussian"):
        raise ValueError(f"method must be 'cog' or 'gaussian', got {o.method!r}")
    if o.centre_on not in ("laser", "luma", "auto"):
        raise ValueError(f"centre_on must be 'laser', 'luma' or 'auto', got {o.centre_on!r}")
    if o.reference not in ("local", "frame"):
        raise ValueError(f"reference must be 'local' or 'frame', got {o.reference!r}")
    if not (0.0 < o.band < 1.0):
        raise ValueError(f"band must be in (0, 1), got {o.band}")
    if not (o.max_width_px > 0):
        raise ValueError(f"max_width_px must be positive, got {o.max_width_px}")
    if not (o.max_width_rel == 0 or o.max_width_rel > 1):
        raise ValueError(f"max_width_rel must be 0 (no test) or > 1, got {o.max_width_rel}")
    if o.min_peak is not None and not (o.min_peak >= 0):
        raise ValueError(f"min_peak must be >= 0, got {o.min_peak}")
    if not (0.0 <= o.tail_fraction < 1.0) or not (o.noise_k >= 0):
        raise ValueError(f"need 0 <= tail_fraction < 1 and noise_k >= 0, got "
                         f"{o.tail_fraction} and {o.noise_k}")
    if int(o.reference_lines) != o.reference_lines or o.reference_lines < 0:
        raise ValueError(f"reference_lines must be an integer >= 0, got {o.reference_lines}")
    if o.s is not None and not (np.isfinite(o.s) and o.s >= 0):
        raise ValueError(f"s must be a finite brightness >= 0, got {o.s}")
    if o.detector not in ("ridge", "band"):
        raise ValueError(f"detector must be 'ridge' or 'band', got {o.detector!r}")
    if o.colour != "auto" and o.colour not in CONTRASTS:
        raise ValueError(f"colour must be 'auto' or one of {CONTRASTS}, got {o.colour!r}")
    if int(o.min_run) != o.min_run or o.min_run < 1:
        raise ValueError(f"min_run must be an integer >= 1, got {o.min_run}")
    if not (o.link_px > 0):
        raise ValueError(f"link_px must be positive, got {o.link_px}")


def extract_stripe_centres(
    image: np.ndarray,
    *,
    background: np.ndarray | None = None,
    roi: np.ndarray | None = None,
    options: StripeOptions = StripeOptions(),
) -> StripePoints:
    """Sub-pixel laser stripe centres, at most one per image column (or row).

    See the module docstring for the method (seed §4.2, eqs. 18–20, then a centre of
    gravity or a Gaussian fit per line).

    Parameters
    ----------
    image : (H, W) or (H, W, 3) uint8, uint16 or float
        The laser-lit frame, mono or RGB, any laser colour.
    background : same shape as ``image``, optional
        Laser-off frame subtracted before anything else: clipped at 0 for the band
        detector; for the ridge detector lifted by a pedestal instead
        (:func:`_subtract_background`), in the image's own type.
    roi : (H, W) bool, optional
        Ridge detector: the region where the stripe can be (the laser sheet inside the
        workspace, :func:`robo3d.triangulation.sheet_roi_mask`); candidates are sought
        only there, in each line between the region's first and last pixel (exact for
        a convex region), for the colour, the axis and the stripe. Lines that do not
        meet it are counted ``outside_roi``. None: the whole image. The band detector
        ignores it.
    options : StripeOptions
        The detector, its colour, axis and thresholds, the sub-pixel estimator (see
        :class:`StripeOptions`). Default: the project's defaults.

    Returns
    -------
    StripePoints
        The centres, their confidence, peak and width, and the rejected lines by reason.
        A frame without a stripe (a black frame, an empty array) gives zero centres,
        not an error.

    References
    ----------
    .. [1] The seed chapter, §4.2, eqs. 18–20.
    .. [2] R. B. Fisher and D. K. Naidu, "A comparison of algorithms for subpixel peak
       detection", 1996.
    .. [3] H. Guo, "A simple algorithm for fitting a Gaussian function", 2011.
    """
    o = options
    image = _check_image(np.asarray(image))
    _check_options(o)
    roi = _check_roi(roi, image.shape)
    full_scale = _full_scale(image.dtype)
    min_peak_abs = 0.04 * full_scale if o.min_peak is None else float(o.min_peak)
    # the ridge detector measures heights against local baselines: the difference keeps
    # its noise (a pedestal); the band detector's eq. 20 band is relative to the
    # brightness: the seed's clipped difference
    work = _subtract_background(image, background, pedestal=o.detector == "ridge")
    img = _as_kernel_image(work)
    if img.dtype == np.float32 and not np.all(np.isfinite(img)):
        raise ValueError("image has non-finite (NaN or inf) pixels")
    h_img, w_img, nch = img.shape
    if img.size == 0:
        ax = "columns" if o.axis == "auto" else o.axis
        return StripePoints.empty(axis=ax, s=float("nan") if o.s is None else float(o.s),
                                  n_lines=w_img if ax == "columns" else h_img,
                                  rejected={"too_weak": w_img if ax == "columns" else h_img})
    if o.detector == "ridge":
        kw = dict(colour=o.colour, min_peak=min_peak_abs,
                  max_width_px=float(o.max_width_px), method=o.method,
                  tail_fraction=float(o.tail_fraction), noise_k=float(o.noise_k),
                  min_run=int(o.min_run), link_px=float(o.link_px), roi=roi,
                  centre_on=o.centre_on, follow=bool(o.follow))
        sp = _extract_ridge(img, axis=o.axis, **kw)
        if o.faint_taps > 1:
            sp = _faint_stripe(img, sp, int(o.faint_taps), kw)
        return _drop_wide(sp, float(o.max_width_rel))
    return _extract_band(img, o, min_peak_abs)


def _faint_stripe(img: np.ndarray, sp: StripePoints, taps: int, kw: dict[str, Any]
                  ) -> StripePoints:
    """Step 9 of the module docstring: a faint stripe in a noisy frame, searched again in
    the frame averaged over ``taps`` pixels along its lines' direction.

    Only where the frame's noise sets the threshold well above ``min_peak`` (``2 noise_k
    sigma > _FAINT_GAIN min_peak``, sigma of the mono frame or of the laser's channel:
    a cheap sensor, a dark object, a blue laser on brown). The average of ``taps``
    pixels along the stripe keeps a straight stripe's height and divides the noise by
    ``sqrt(taps)``, so the threshold falls by that much (the mean is taken at three
    slopes across the lines, and the largest kept per pixel and channel:
    :func:`_faint_kernels`); the curves must be twice ``min_run`` long. Along the
    first search's axis (the stage fixes it from the laser's geometry), in its colour
    (the colour tests apply to the averaged channels). Its centres in
    the lines the first search left without a centre are added (the first search's
    stay: a clear stripe is not averaged), with the confidence scaled by
    ``1 / sqrt(taps)`` and flagged ``faint``; those on texture are not
    (:data:`_FAINT_MAX_SPREAD`). Measured (``benchmarks/README.md``, stops 42 and 43): a
    blue laser on a brown fin seen by a monochrome camera (noise 4.2 DN, threshold 25
    DN, the stripe 12-40 DN high), 1.5 % of the true stripe's lines found before, 41 %
    after; a red laser on a black torus in PNG colour frames (the stripe 7-24 DN), 29 %
    -> 53 % of its one-pixel bins."""
    nch = img.shape[2]
    if nch == 1:
        k, ch = _LIGHTNESS, 0
    elif sp.colour in CONTRASTS[:3]:
        k = ch = CONTRASTS.index(sp.colour)
    else:  # the lightness of an RGB frame (a white laser): not searched so
        return sp
    if _fast8(img, k):
        sigma = float(_noise8(img, k))
    else:
        sigma = float(_noise_contrast(img, k, False))
    noise_k, min_peak = float(kw["noise_k"]), float(kw["min_peak"])
    # the detector's estimate is the median's integer bin; the interpolated one lies
    # within half a level of it (read only where it could pass: a clean frame's cost)
    if not 2.0 * noise_k * (sigma + _HALF_LEVEL_SIGMA) > _FAINT_GAIN * min_peak:
        return sp
    if not 2.0 * noise_k * _smooth_sigma(img[:, :, ch]) > _FAINT_GAIN * min_peak:
        return sp
    import cv2

    taps = 2 * (taps // 2) + 1  # centred on the pixel: an even count is the next odd one
    g = 1.0 / np.sqrt(taps)
    # the mean along the stripe at three slopes across the lines (-0.5, 0, 0.5 px per
    # px), the largest of the three per pixel: a stripe up to 45 degrees off the lines,
    # or bent, meets one of them within a quarter pixel per pixel
    # (an RGB frame's channels each take their own largest mean: the laser's channel
    # its stripe's slope, the others at least as much as at that slope, so that the
    # colour test, the laser's channel rising more than the others, is not loosened)
    smooth = None
    for kernel in _faint_kernels(taps, sp.axis == "columns"):
        m = cv2.filter2D(img[:, :, 0] if nch == 1 else img, -1, kernel,
                         borderType=cv2.BORDER_REPLICATE)
        smooth = m if smooth is None else np.maximum(smooth, m)
    smooth = np.ascontiguousarray(smooth.reshape(img.shape))
    # the threshold from the frame's own noise (the smoothed frame's differences along
    # the smoothing are correlated: its own estimate would be too low for rows)
    thr = max(min_peak, 2.0 * noise_k * sigma * g)
    sp2 = _extract_ridge_axis(smooth, axis=sp.axis, **{
        **kw, "min_peak": thr, "noise_k": 0.0, "min_run": 2 * int(kw["min_run"]),
        "follow": False, "colour": sp.colour if nch == 3 else kw["colour"]})
    # a stripe faint enough to need this adds about 3 sigma at most to the spread of its
    # neighbourhood; more is texture (a marker's cells, a print), whose edges the
    # averaged search can take for a stripe
    spread = _local_spread(img[:, :, ch], sp2.u, sp2.v, _FAINT_SPREAD_HALF)
    textured = spread > _FAINT_MAX_SPREAD * sigma
    # only the lines the first search left without a centre: its own centres stay
    empty_line = ~np.isin(sp2.line, sp.line)
    add = ~textured & empty_line
    if not add.any():
        return sp
    rejected = dict(sp.rejected)
    rejected["textured"] += int(np.count_nonzero(textured & empty_line))
    line = np.concatenate([sp.line, sp2.line[add]])
    order = np.argsort(line, kind="stable")

    def cat(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return np.concatenate([a, b[add]])[order]

    angle = sp.angle_deg if np.isfinite(sp.angle_deg) else sp2.angle_deg
    return StripePoints(u=cat(sp.u, sp2.u), v=cat(sp.v, sp2.v),
                        confidence=cat(sp.confidence, sp2.confidence * g),
                        peak=cat(sp.peak, sp2.peak), width_px=cat(sp.width_px, sp2.width_px),
                        skew_px=cat(sp.skew_px, sp2.skew_px), line=line[order],
                        axis=sp.axis, s=sp.s, n_lines=sp.n_lines, rejected=rejected,
                        colour=sp.colour, angle_deg=angle,
                        faint=np.concatenate([sp.faint, np.ones(int(add.sum()), bool)])[order])


#: :func:`_faint_stripe` runs only where the frame's noise sets a threshold this many
#: times ``min_peak`` or more: there the average lowers it by a third or more. Below, it
#: gains little and costs much: the ambient-lit speed frames (1280 x 960 RGB, noise 1.0-1.6
#: grey levels, threshold 6.3-9.4) took 1.3 -> 2.9 ms per frame for 0.3 centres more.
_FAINT_GAIN = 1.5
#: half a grey level of the median absolute difference, as a noise sigma
#: (``1.4826 * 0.5 / sqrt(2)``): how far :func:`_smooth_sigma` can lie above
#: :func:`_noise8`'s estimate, whose median is the integer level it falls in
_HALF_LEVEL_SIGMA = 0.53

#: :func:`_faint_stripe`'s texture test: a centre whose (2 h + 1)^2 neighbourhood in the
#: frame (h = 3) spreads more than this many noise sigmas (its standard deviation) lies
#: on texture. Measured on random scenes 142 and 243 (markers, a checker print): 89 % of
#: the averaged search's centres more than 3 px off the true stripe go, 5 % of those
#: within 1.5 px of it.
_FAINT_MAX_SPREAD = 6.0
_FAINT_SPREAD_HALF = 3


def _smooth_sigma(channel: np.ndarray) -> float:
    """The noise sigma of a 2-D image as :func:`_noise8` samples it (the median absolute
    difference of vertically adjacent pixels on a 64 x 64 grid), the median of integer
    differences interpolated within its bin (grouped data): the detector's own estimate
    jumps between 1.05 and 2.1 grey levels where the true sigma is about 1.5, and
    :func:`_faint_stripe`'s gate must not follow that jump."""
    h, w = channel.shape
    if h < 2 or w == 0:
        return 0.0
    r, c = _noise_grid.py_func(h, w)  # the detector's samples (64 of each: no kernel)
    d = np.abs(channel[np.ix_(r + 1, c)].astype(np.float64) - channel[np.ix_(r, c)]).ravel()
    if not np.issubdtype(channel.dtype, np.integer):
        return float(_mad_sigma.py_func(d))
    counts = np.bincount(d.astype(np.int64))
    cum = np.cumsum(counts)
    half = d.size / 2.0
    v = int(np.searchsorted(cum, half, side="right"))  # the bin holding the median
    below = cum[v - 1] if v > 0 else 0
    lo, width = (0.0, 0.5) if v == 0 else (v - 0.5, 1.0)
    med = lo + (half - below) / max(counts[v], 1) * width
    return float(1.4826 * med / np.sqrt(2.0))


def _local_spread(img: np.ndarray, u: np.ndarray, v: np.ndarray, half: int) -> np.ndarray:
    """The standard deviation of ``img`` (2-D) over the (2 half + 1)^2 pixels around each
    point (u, v) (clipped at the image's border)."""
    if not len(u):
        return np.zeros(0)
    h, w = img.shape
    d = np.arange(-half, half + 1)
    rows = np.clip(np.rint(v).astype(np.int64)[:, None, None] + d[None, :, None], 0, h - 1)
    cols = np.clip(np.rint(u).astype(np.int64)[:, None, None] + d[None, None, :], 0, w - 1)
    return img[rows, cols].reshape(len(u), -1).astype(np.float64).std(axis=1)


def _subset(sp: StripePoints, keep: np.ndarray, reason: str) -> StripePoints:
    """``sp`` with the centres ``keep`` only, the others counted as ``reason``."""
    if keep.all():
        return sp
    rejected = dict(sp.rejected)
    rejected[reason] += int(np.count_nonzero(~keep))
    return StripePoints(u=sp.u[keep], v=sp.v[keep], confidence=sp.confidence[keep],
                        peak=sp.peak[keep], width_px=sp.width_px[keep],
                        skew_px=sp.skew_px[keep], line=sp.line[keep],
                        axis=sp.axis, s=sp.s, n_lines=sp.n_lines, rejected=rejected,
                        colour=sp.colour, angle_deg=sp.angle_deg, faint=sp.faint[keep],
                        v_sensor=None if sp.v_sensor is None else sp.v_sensor[keep])


def _faint_kernels(taps: int, along_u: bool) -> list[np.ndarray]:
    """:func:`_faint_stripe`'s means of ``taps`` pixels along lines of slope -0.5, 0 and
    0.5 across the search lines (bilinear between pixels), as ``cv2.filter2D`` kernels:
    along ``u`` (one centre per column) or, transposed, along ``v``."""
    half = taps // 2
    out = []
    for slope in (-0.5, 0.0, 0.5):
        k = np.zeros((2 * half + 1, taps), np.float32)
        for i, du in enumerate(range(-half, half + 1)):
            dv = slope * du
            lo = int(np.floor(dv))
            frac = dv - lo
            k[half + lo, i] += (1.0 - frac) / taps
            if frac > 0:
                k[half + lo + 1, i] += frac / taps
        out.append(k if along_u else np.ascontiguousarray(k.T))
    return out


#: :func:`_drop_wide` tests a frame's widths only when it has this many centres (the
#: median of fewer says little about the stripe's own width)
_WIDE_MIN_CENTRES = 16


def skewed_centres(skew_px: np.ndarray, max_skew_px: float, max_fraction: float
                   ) -> tuple[np.ndarray, float, bool]:
    """Which centres were pulled off their stripe (module docstring, step 5c): skew more
    than ``max_skew_px`` from the median of the known skews (NaN: not known, never
    skewed). Returns the mask, the median and whether the test applies: not when more
    than ``max_fraction`` of the centres would go (the stripe's profile is lopsided
    throughout, not pulled off locally; the mask is then all false), nor when
    ``max_skew_px`` is 0 or no skew is known."""
    skew = np.asarray(skew_px, dtype=np.float64).reshape(-1)
    known = skew[np.isfinite(skew)]
    none = np.zeros(skew.size, bool)
    if max_skew_px <= 0 or not known.size:
        return none, float("nan"), False
    centre = float(np.median(known))
    bad = np.abs(skew - centre) > max_skew_px
    if bad.mean() > max_fraction:
        return none, centre, False
    return bad, centre, True


def _drop_wide(sp: StripePoints, rel: float) -> StripePoints:
    """``sp`` without the centres wider than ``rel`` times the median width of its
    centres (module docstring, step 5b), counted ``too_wide``."""
    if rel <= 0 or len(sp) < _WIDE_MIN_CENTRES:
        return sp
    n = len(sp)  # the upper median (np.partition: a third of np.median's time)
    wide = sp.width_px > rel * float(np.partition(sp.width_px, n // 2)[n // 2])
    return _subset(sp, ~wide, "too_wide")


def _extract_band(img: np.ndarray, o: StripeOptions, min_peak_abs: float) -> StripePoints:
    """The band detector (the seed as written, module docstring) on an (H, W, 1|3) kernel
    image, ``min_peak_abs`` in its units."""
    axis, s, band, max_width_px = o.axis, o.s, o.band, o.max_width_px
    nch = img.shape[2]
    # pass 1: the lines' brightest pixels (and the rows' for "auto")
    # the rows' extrema: to choose the axis, and to skip the rows of pass 2 that cannot
    # reach any line's band (cheap for mono images, whose reductions vectorise)
    want_rows = nch == 1
    if axis == "auto":
        _, axis, _ = _choose_contrast(img, (_LIGHTNESS,), "auto", min_peak_abs)
    if axis == "rows":
        img = _transpose(img)
    cmax, carg, cmin, rmax, rmin = _scan_peaks(img, want_rows)
    sigma_n = float(_noise_sigma(img, nch))
    n_lines = img.shape[1]
    good = (cmax - cmin) >= np.float32(min_peak_abs)
    lines_idx = np.flatnonzero(good)

    # eq. 18 on the samples (the good lines' brightest pixels), or the caller's s
    if s is None and nch == 1:  # eq. 18 of grey samples: their mean (= their lightness)
        s_frame = float(cmax[lines_idx].mean(dtype=np.float64)) if lines_idx.size else 0.0
    elif s is None:
        s_frame = _eq18(img, carg[lines_idx], lines_idx) if lines_idx.size else 0.0
    else:
        s_frame = float(s)
    if s is not None or o.reference == "frame":
        s_ref = np.full(n_lines, s_frame, dtype=np.float32)
    else:
        s_ref = _local_reference(cmax, good, int(o.reference_lines))
    lo = ((1.0 - band) * s_ref).astype(np.float32)
    hi = ((1.0 + band) * s_ref).astype(np.float32)

    # pass 2: the band's pixels per line; then the centres, line by line
    if not lines_idx.size:
        rows = np.zeros(0, dtype=np.int64)
    elif rmax.size:
        rows = np.flatnonzero(rmax >= lo[lines_idx].min()).astype(np.int64)
    else:
        rows = np.arange(img.shape[0], dtype=np.int64)
    n_above, n_band, barg = _scan_band(img, nch, lo, hi, good, rows)
    h = int(np.ceil(1.1 * max_width_px)) + 2
    status, centre, amp, width, top = _centres(
        img, nch, good, carg, lo, hi, n_above, n_band, barg, h, _H_SMALL,
        float(o.tail_fraction),
        float(o.noise_k * sigma_n), float(min_peak_abs), float(max_width_px),
        o.method == "gaussian")

    counts = np.bincount(status, minlength=len(REJECTION_REASONS) + 1)
    rejected = {name: int(counts[i + 1]) for i, name in enumerate(REJECTION_REASONS)}
    ok = np.flatnonzero(status == _OK)
    amp_g, width_g = amp[ok], width[ok]
    c_snr = 1.0 - np.exp(-amp_g / (10.0 * max(sigma_n, 1e-12)))
    c_width = np.clip(2.0 - 2.0 * width_g / max_width_px, 0.0, 1.0)
    c_peak = np.clip(amp_g / max((1.0 - band) * s_frame, 1e-12), 0.0, 1.0)
    conf = np.clip(c_snr * c_width * c_peak, 0.0, 1.0)
    line_idx = ok.astype(np.int64)
    if axis == "columns":
        u, v = line_idx.astype(np.float64), centre[ok]
    else:
        u, v = centre[ok], line_idx.astype(np.float64)
    return StripePoints(u=u, v=v, confidence=conf, peak=amp_g, width_px=width_g,
                        skew_px=centre[ok] - top[ok], line=line_idx, axis=axis, s=s_frame,
                        n_lines=n_lines,
                        rejected=rejected, colour="lightness",
                        angle_deg=_angle_deg(u, v, line_idx, axis == "rows"))


def _angle_deg(u: np.ndarray, v: np.ndarray, line: np.ndarray | None = None,
               rows: bool = False, slope: float | None = None) -> float:
    """Direction of the stripe, degrees from u towards v, in (-90, 90]: the median slope
    between centres of neighbouring lines (robust to a second piece of stripe elsewhere
    in the frame; ``slope``: that median when already known), else the principal axis
    of the points."""
    if u.size < 2:
        return float("nan")
    if line is not None and slope is None:
        along, across = (v, u) if rows else (u, v)
        nb = np.flatnonzero(np.diff(line) == 1)
        if nb.size >= 3:
            slope = float(np.median(across[nb + 1] - across[nb]))
    if line is not None and slope is not None:
        du, dv = (slope, 1.0) if rows else (1.0, slope)
        ang = float(np.degrees(np.arctan2(dv, du)))
        return ang - 180.0 if ang > 90.0 else (ang + 180.0 if ang <= -90.0 else ang)
    du, dv = u - u.mean(), v - v.mean()
    suu, svv, suv = float(du @ du), float(dv @ dv), float(du @ dv)
    ang = 0.5 * np.degrees(np.arctan2(2.0 * suv, suu - svv))
    return float(90.0 if ang <= -90.0 else ang)


def _choose_contrast(img: np.ndarray, ks: Sequence[int], axis: str, thr: float,
                     spans: tuple[np.ndarray, ...] | None = None,
                     ) -> tuple[int, str, dict[str, float]]:
    """The contrast and the axis in which the stripe is the most consistent ridge, from
    every ``step``-th row and column (``step``: about 1/48 of the image's smaller side)."""
    h, w, nch = img.shape
    step = max(4, int(round(min(h, w) / 48)))
    if spans is None:
        spans = _spans(None, h, w)
    scores, axes = {}, {}
    for k in ks:
        s_rows, s_cols = _probe(img, k, step, thr, spans)
        s_rows = s_rows if axis in ("auto", "rows") else -1.0
        s_cols = s_cols if axis in ("auto", "columns") else -1.0
        scores[k] = max(s_rows, s_cols)
        axes[k] = axis if axis != "auto" else ("rows" if s_rows > s_cols else "columns")
    # a laser colour before the lightness, unless the lightness ridge is far more
    # consistent (a white or infrared laser, a grey image): the lightness also sees
    # every thin bright thing of the scene (a white edge, a lamp, a glint)
    colours = [k for k in ks if k != _LIGHTNESS]
    k_best = max(colours, key=lambda k: scores[k]) if colours else _LIGHTNESS
    if _LIGHTNESS in scores and scores[_LIGHTNESS] > _LIGHTNESS_PREFERRED * scores[k_best]:
        k_best = _LIGHTNESS
    if scores[k_best] <= 0 and axis == "auto":
        axes[k_best] = "columns"
    return k_best, axes[k_best], {CONTRASTS[k]: v for k, v in scores.items()}


def _spans(roi: np.ndarray | None, h: int, w: int) -> tuple[np.ndarray, ...]:
    """The region of interest as per-line spans: rows [clo, chi] of each column and
    columns [rlo, rhi] of each row (the whole image when ``roi`` is None). A convex
    region is exactly its spans; another is searched within its lines' extents."""
    if roi is None:
        return (np.zeros(w, np.int32), np.full(w, h - 1, np.int32),
                np.zeros(h, np.int32), np.full(h, w - 1, np.int32))
    return _roi_spans(roi)


def _check_roi(roi: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray | None:
    if roi is None:
        return None
    roi = np.asarray(roi)
    if roi.shape != tuple(shape[:2]):
        raise ValueError(f"roi must be a (H, W) mask like the image {tuple(shape[:2])}, "
                         f"got shape {roi.shape}")
    return np.ascontiguousarray(roi if roi.dtype == np.bool_ else roi != 0)


def _extract_ridge(img: np.ndarray, *, axis: str, **kw: Any) -> StripePoints:
    """The ridge detector on an (H, W, 1|3) kernel image (see the module docstring),
    candidates only inside ``roi`` when given.

    With ``axis="auto"``, when the probe's axis crosses two curves in far more of its
    lines than it kept (``two_blobs`` and ``second_line`` more than
    ``_AXIS_RETRY_CROSSED`` times the centres: a stripe bent into a U, the laser's arc
    inside a cup, runs both ways, and the probe's strongest curve is one of its steep
    arms), the frame is searched along the other axis too, and that result is kept when
    it has more centres and is consistent (fewer such lines than centres); step 4 of
    the module docstring."""
    first = _extract_ridge_axis(img, axis=axis, **kw)
    if axis != "auto":
        return first
    if _crossed(first) <= _AXIS_RETRY_CROSSED * len(first.u):
        return first
    # the same contrast as the first search (with colour "auto" the other axis could vote
    # for another one)
    other = _extract_ridge_axis(img, axis="rows" if first.axis == "columns" else "columns",
                                **{**kw, "colour": first.colour})
    better = len(other.u) > len(first.u) and _crossed(other) < len(other.u)
    return other if better else first


#: :func:`_extract_ridge`: lines crossing two curves, per centre kept, beyond which the
#: other axis is searched too. Simulated cup/4 (the arc inside the cup, frames 389-390):
#: 133 such lines for 6-7 centres (the other axis: 153-182 centres). At 1 the blue cell
#: (a 30-degree stripe beside a glinting blue edge, 1.2-1.5 crossings per centre) went
#: to the other axis in 4 more frames and took the edge's glints: outliers 0.65 -> 0.79 %.
_AXIS_RETRY_CROSSED = 3.0


def _crossed(sp: StripePoints) -> int:
    """Lines of a frame that crossed two curves (``two_blobs``, ``second_line``)."""
    return int(sp.rejected["two_blobs"] + sp.rejected["second_line"])


def _extract_ridge_axis(img: np.ndarray, *, axis: str, colour: str, min_peak: float,
                        max_width_px: float, method: str, tail_fraction: float,
                        noise_k: float, min_run: int, link_px: float,
                        roi: np.ndarray | None = None,
                        centre_on: str = "laser", follow: bool = False) -> StripePoints:
    """:func:`_extract_ridge` along ``axis`` (``"auto"``: the probe's choice)."""
    h_img, w_img, nch = img.shape
    spans = _spans(roi, h_img, w_img)
    if nch == 1:
        ks: tuple[int, ...] = (_LIGHTNESS,)
    elif colour == "auto":
        ks = (0, 1, 2, _LIGHTNESS)
    else:
        ks = (CONTRASTS.index(colour),)
    k = ks[0]
    if len(ks) > 1:
        k, axis, _ = _choose_contrast(img, ks, axis, min_peak, spans)
    name = CONTRASTS[k]
    clo, chi, rlo, rhi = spans
    h = int(np.ceil(1.1 * max_width_px)) + 2
    if _fast8(img, k):  # uint8, a laser colour or mono: one compiled call (no GIL)
        step = max(4, int(round(min(h_img, w_img) / 48)))
        (rows_axis, sigma_n, win, status, run, n_second, n_isolated, st2, centre, amp,
         width, top) = _ridge_frame8(img, k, ("auto", "rows", "columns").index(axis), step,
                                float(min_peak), float(noise_k), float(link_px),
                                int(min_run), h, float(tail_fraction), float(max_width_px),
                                method == "gaussian", clo, chi, rlo, rhi, follow)
        axis = "rows" if rows_axis else "columns"
        lo, hi = (rlo, rhi) if rows_axis else (clo, chi)
        if centre_on == "luma" and nch == 3 and k != _LIGHTNESS:
            centre = _luma_centres(img, rows_axis, np.where(st2 == _OK, win, -1), h,
                                   centre, float(tail_fraction), float(noise_k),
                                   float(min_peak), float(max_width_px),
                                   method == "gaussian")
        (status, counts, line_idx, across, amp_c, width_g, skew, c_width, c_peak, c_run, sums,
         slope) = _ridge_tail8(img, rows_axis, status, st2, lo, hi, centre, amp, width, top,
                               run, int(min_run), float(max_width_px))
        rejected = {nm: int(counts[i + 1]) for i, nm in enumerate(REJECTION_REASONS)}
        rejected["isolated"] += int(n_isolated)
        rejected["second_line"] += int(n_second)
        c_snr = 1.0 - np.exp(-amp_c / (10.0 * max(float(sigma_n), 1e-12)))
        conf = np.clip(c_snr * c_width * c_peak * c_run, 0.0, 1.0)
        along = line_idx.astype(np.float64)
        u, v = (across, along) if rows_axis else (along, across)
        means = sums / max(line_idx.size, 1)  # eq. 18 (as _eq18)
        s_frame = float((means.max() + means.min()) / 2.0) if line_idx.size else float("nan")
        return StripePoints(u=u, v=v, confidence=conf, peak=amp_c, width_px=width_g,
                            skew_px=skew, line=line_idx, axis=axis, s=s_frame,
                            n_lines=win.size,
                            rejected=rejected, colour=name,
                            angle_deg=_angle_deg(u, v, line_idx, rows_axis,
                                                 None if np.isnan(slope) else float(slope)))
    else:
        if axis == "auto":
            k, axis, _ = _choose_contrast(img, ks, axis, min_peak, spans)
        # one pass over the image: the contrast, its ridges, two candidates per line
        two = nch == 3 and img.dtype == np.uint8 and k == _LIGHTNESS
        scale = 2.0 if two else 1.0
        wdt = np.int16 if img.dtype == np.uint8 else np.float32
        sigma_n = float(_noise_contrast(img, k, two))
        thr = max(scale * min_peak, 2.0 * noise_k * sigma_n)
        thr_w = wdt(np.ceil(thr)) if wdt is np.int16 else np.float32(thr)
        sep = _RIDGE_A2 + 1
        sat = wdt(_saturation(img.dtype))
        if axis == "rows":
            lo, hi = rlo, rhi
            m1, p1, m2, p2 = _ridge_scan_rows(img, k, two, np.zeros(w_img, wdt),
                                              _RIDGE_A1, _RIDGE_A2, sep, thr_w, sat, lo, hi)
        else:
            lo, hi = clo, chi
            ring = np.zeros((2 * _RIDGE_A2 + 1, w_img), wdt)
            m1, p1, m2, p2 = _ridge_scan_cols(img, k, two, ring, _RIDGE_A1, _RIDGE_A2, sep,
                                              thr_w, sat, lo, hi)
        n_lines = m1.size
        win, status, run, n_second, n_isolated, _ = _link(m1, p1, m2, p2, sep,
                                                          float(link_px), _LINK_GAP,
                                                          int(min_run), True)
        if follow:
            _extend(img, k, axis == "rows", win, status, run, float(thr_w), float(link_px),
                    _LINK_GAP, lo, hi, float(sat))
        st2, centre, amp, width, top = _ridge_centres(img, k, two, axis == "rows", win, h,
                                                 _H_SMALL, float(tail_fraction),
                                                 float(noise_k * sigma_n),
                                                 float(scale * min_peak),
                                                 float(max_width_px), method == "gaussian")
    if centre_on == "luma" and nch == 3 and k != _LIGHTNESS:
        centre = _luma_centres(img, axis == "rows", np.where(st2 == _OK, win, -1), h,
                               centre, float(tail_fraction), float(noise_k),
                               float(min_peak), float(max_width_px), method == "gaussian")
    status = np.where(status == _OK, st2, status)
    status = np.where((status == _TOO_WEAK) & (lo > hi), np.int8(_OUTSIDE), status)
    counts = np.bincount(status, minlength=len(REJECTION_REASONS) + 1)
    rejected = {nm: int(counts[i + 1]) for i, nm in enumerate(REJECTION_REASONS)}
    rejected["isolated"] += int(n_isolated)
    rejected["second_line"] += int(n_second)
    ok = np.flatnonzero(status == _OK)
    amp_c, width_g = amp[ok], width[ok]
    c_snr = 1.0 - np.exp(-amp_c / (10.0 * max(sigma_n, 1e-12)))
    c_width = np.clip(2.0 - 2.0 * width_g / max_width_px, 0.0, 1.0)
    c_peak = np.clip(amp_c / max(float(np.median(amp_c)) if ok.size else 1.0, 1e-12), 0, 1)
    c_run = np.clip(run[ok] / (2.0 * min_run), 0.0, 1.0)
    conf = np.clip(c_snr * c_width * c_peak * c_run, 0.0, 1.0)
    line_idx = ok.astype(np.int64)
    if axis == "columns":
        u, v = line_idx.astype(np.float64), centre[ok]
    else:
        u, v = centre[ok], line_idx.astype(np.float64)
    s_frame = float("nan")
    if ok.size:  # eq. 18 on the centres' pixels of the (background-subtracted) frame
        rr = np.clip(np.rint(v).astype(np.int64), 0, h_img - 1)
        cc = np.clip(np.rint(u).astype(np.int64), 0, w_img - 1)
        s_frame = _eq18(img, rr, cc)
    return StripePoints(u=u, v=v, confidence=conf, peak=amp_c / scale, width_px=width_g,
                        skew_px=centre[ok] - top[ok], line=line_idx, axis=axis, s=s_frame,
                        n_lines=n_lines,
                        rejected=rejected, colour=name,
                        angle_deg=_angle_deg(u, v, line_idx, axis == "rows"))


def _luma_centres(img: np.ndarray, rows_axis: bool, win: np.ndarray, h: int,
                  centre: np.ndarray, tail_fraction: float, noise_k: float,
                  min_peak: float, max_width_px: float, gaussian: bool) -> np.ndarray:
    """The lines' centres re-taken on the luma profile (see the module docstring, step
    5): where the luma has a peak of its own (the same tests as the laser channel's)
    within 1.5 px of the laser channel's centre; elsewhere the centre is kept."""
    sigma_y = float(_noise_contrast(img, _LUMA, False))
    st_y, c_y, _, _, _ = _ridge_centres(img, _LUMA, False, rows_axis, win, h, _H_SMALL,
                                     tail_fraction, noise_k * sigma_y, min_peak,
                                     max_width_px, gaussian)
    use = (st_y == _OK) & (win >= 0) & (np.abs(c_y - centre) <= 1.5)
    return np.where(use, c_y, centre)


def centre_on_for(centre_on: str, encoded: bytes | None) -> str:
    """``stripes.centre_on`` resolved for frames encoded like ``encoded`` (one frame's
    recorded bytes): ``auto`` is ``luma`` for a JPEG whose colour is stored at lower
    resolution than its luma (:func:`robo3d.recording.images.chroma_subsampled`), else
    ``laser``; ``laser`` and ``luma`` stay."""
    if centre_on != "auto":
        return centre_on
    from .recording.images import chroma_subsampled

    return "luma" if encoded is not None and chroma_subsampled(encoded) else "laser"


def estimate_laser_colour(images: Sequence[np.ndarray], *,
                          backgrounds: Sequence[np.ndarray | None] | None = None,
                          min_peak: float | None = None,
                          rois: Sequence[np.ndarray | None] | None = None,
                          axes: Sequence[str | None] | None = None,
                          ) -> tuple[str, dict[str, float]]:
    """The laser's colour in a set of laser frames: the contrast of :data:`CONTRASTS`
    in which the stripe is, summed over the frames, the most consistent ridge.

    Per frame, every 1/48-th row and column is searched for its strongest ridge of each
    contrast (see :func:`extract_stripe_centres`); a contrast scores the heights of the
    ridges that continue from one sampled line to the next (the stripe, not clutter).
    The lightness is chosen only when it scores 8 times the best colour (a white or
    infrared laser, grey images): it also sees every thin bright thing of a scene.

    Parameters
    ----------
    images : sequence of (H, W) or (H, W, 3) arrays
        A few laser frames of one recording.
    backgrounds : sequence of arrays or None, optional
        The laser-off frame of each image (subtracted, clipped at 0), or None.
    min_peak : float, optional
        Smallest ridge height counted, in the images' units (default 4 % of full scale).
    rois : sequence of (H, W) bool or None, optional
        Each image's region of interest (see :func:`extract_stripe_centres`): only
        ridges inside it vote (a coloured object's lit rim outside the laser sheet's
        band does not). None: the whole images.
    axes : sequence of {"columns", "rows", None}, optional
        Each image's scan axis where the laser's geometry fixes it
        (:func:`robo3d.triangulation.epipolar_axis`): only ridges across that axis's lines
        vote (a printed pattern's lines along them are not the stripe). None: both.

    Returns
    -------
    colour : str
        One of :data:`CONTRASTS` (``"lightness"`` for mono images or without frames).
    scores : dict of str to float
        The summed score of each contrast.
    """
    totals: dict[str, float] = {}
    if backgrounds is None:
        backgrounds = [None] * len(images)
    if len(backgrounds) != len(images):
        raise ValueError(f"need one background per image, got {len(backgrounds)} for "
                         f"{len(images)} images")
    if rois is None:
        rois = [None] * len(images)
    if len(rois) != len(images):
        raise ValueError(f"need one roi per image, got {len(rois)} for {len(images)} images")
    if axes is None:
        axes = [None] * len(images)
    if len(axes) != len(images):
        raise ValueError(f"need one axis per image, got {len(axes)} for {len(images)} images")
    for image, bg, roi, ax in zip(images, backgrounds, rois, axes, strict=True):
        image = _check_image(np.asarray(image))
        img = _as_kernel_image(_subtract_background(image, bg, pedestal=True))
        if img.size == 0:
            continue
        thr = 0.04 * _full_scale(image.dtype) if min_peak is None else float(min_peak)
        ks = (0, 1, 2, _LIGHTNESS) if img.shape[2] == 3 else (_LIGHTNESS,)
        roi = _check_roi(roi, img.shape)
        spans = _spans(roi, img.shape[0], img.shape[1])
        _, _, scores = _choose_contrast(img, ks, ax or "auto", thr, spans)
        for name, v in scores.items():
            totals[name] = totals.get(name, 0.0) + max(v, 0.0)
    colours = [c for c in CONTRASTS[:3] if c in totals]
    if not colours:
        return "lightness", totals
    best = max(colours, key=lambda c: totals[c])
    if totals.get("lightness", 0.0) > _LIGHTNESS_PREFERRED * totals[best]:
        best = "lightness"
    return best, totals


#: :func:`laser_colour_contested`: the runner-up colour's score, as a share of the best's,
#: from which the choice is checked against images of the scene without the laser. In the
#: random scenes 463-982 with views the runner-up reaches it in 4 of 110 (a blue laser on
#: an orange checker, 977: red 979, blue 763); elsewhere it is 1/8 of the best or less.
_COLOUR_CONTESTED = 0.25


def laser_colour_contested(scores: Mapping[str, float]) -> bool:
    """Whether :func:`estimate_laser_colour`'s scores leave the colour in doubt: the
    runner-up laser colour scores at least a quarter of the best (a coloured texture's
    ridges can outscore a laser that its surface barely reflects)."""
    v = sorted((max(float(scores.get(c, 0.0)), 0.0) for c in CONTRASTS[:3]), reverse=True)
    return v[0] > 0 and v[1] >= _COLOUR_CONTESTED * v[0]


def lightness_contested(scores: Mapping[str, float]) -> bool:
    """Whether :func:`estimate_laser_colour` chose the lightness over laser colours that
    did score (colour frames): a laser colour is there, and the lightness can be the
    scene's texture (random scene 1113: a speckled blue laser on an orange checker block,
    lightness 1044 against blue 101: the lightness ridges were the checker's squares)."""
    v = [max(float(scores.get(c, 0.0)), 0.0) for c in CONTRASTS[:3] if c in scores]
    return bool(v) and max(v) > 0 and (
        float(scores.get("lightness", 0.0)) > _LIGHTNESS_PREFERRED * max(v))


def image_level(images: Sequence[np.ndarray],
                rois: Sequence[np.ndarray | None] | None = None) -> float:
    """The images' typical level: the median over the images of each one's median value
    (all channels) inside its region of interest (the whole image where None); 0 without
    pixels."""
    if rois is None:
        rois = [None] * len(images)
    levels = []
    for image, roi in zip(images, rois, strict=True):
        a = np.asarray(image)
        a = a if roi is None else a[np.asarray(roi, dtype=bool)]
        if a.size:
            levels.append(float(np.median(a)))
    return float(np.median(levels)) if levels else 0.0


def laser_colour_beyond_scene(scores: Mapping[str, float], level: float, n_images: int,
                              scene_scores: Mapping[str, float], scene_level: float,
                              n_scene: int, *, lightness: bool = False
                              ) -> tuple[str | None, dict[str, Any]]:
    """The laser's colour as what the laser frames show beyond the scene's own texture.

    ``scene_scores`` are :func:`estimate_laser_colour`'s scores on images of the same
    scene without the laser (the recording's views), searched in the same band. A
    texture's ridges (an orange checker's squares, in the red contrast) score there as
    they do in the laser frames; the laser's do not. Each colour's excess is its laser
    score less its scene score, scaled to the laser frames' number and level (views are
    exposed brighter than laser frames in room light, and a texture's ridge heights grow
    with the light). Random scene 977 (a blue laser on an orange checker bottle): laser
    frames red 979, blue 763; views red 1796, blue 310; scale 0.68: excess red -247,
    blue 551.

    With ``lightness`` (the laser frames chose it over the colours,
    :func:`lightness_contested`) the lightness competes too, by the frames' own rule: it
    stays when its excess is positive and more than :data:`_LIGHTNESS_PREFERRED` times
    the best colour's (a white laser: the colours show nothing beyond the scene). Else
    the colour with the largest excess among those the laser frames show at all (that
    scored) is returned, even where that excess is not positive: the lightness is
    preferred to a colour only on evidence of its own, and here the scene explains it.
    Random scene 1113 (a speckled blue laser on an orange checker block): laser frames
    lightness 1044, blue 101, red 79; views lightness 6398, red 5682, blue 0; scale
    0.68: excess lightness -3335, red -3811, blue 102.

    Returns
    -------
    colour : str or None
        The contrast with the largest excess, or None when no colour shows more in the
        laser frames than in the scene (nothing to decide by; never with
        ``lightness``).
    detail : dict
        ``scale``, ``scene_scores`` and ``excess`` per contrast (for the report).
    """
    names = CONTRASTS if lightness else CONTRASTS[:3]
    if n_scene < 1 or n_images < 1:
        return None, {"scale": None, "scene_scores": dict(scene_scores), "excess": None}
    scale = (n_images / n_scene) * max(float(level), 1.0) / max(float(scene_level), 1.0)
    excess = {c: float(scores.get(c, 0.0)) - scale * float(scene_scores.get(c, 0.0))
              for c in names}
    # with the lightness: a colour the laser frames show at all (one that scored)
    shown = [c for c in CONTRASTS[:3] if not lightness or float(scores.get(c, 0.0)) > 0]
    best = max(shown or CONTRASTS[:3], key=lambda c: excess[c])
    detail = {"scale": round(scale, 4),
              "scene_scores": {c: round(float(scene_scores.get(c, 0.0)), 1) for c in names},
              "excess": {c: round(v, 1) for c, v in excess.items()}}
    if lightness:
        return ("lightness" if excess["lightness"] > _LIGHTNESS_PREFERRED * max(
            excess[best], 0.0) else best), detail
    return (best if excess[best] > 0 else None), detail


#: The laser colour's check by motion (:func:`laser_colour_by_motion`): a contrast's
#: ridges "move with the camera" when its centres in one frame lie within
#: :data:`_MOTION_NEAR_PX` of the other frame's and this many times closer as they are
#: than shifted by the scene's image motion, and "move with the scene" when shifted they
#: lie this many times closer.
_MOTION_RATIO = 2.0
_MOTION_NEAR_PX = 3.0
#: ... a pair of frames tells nothing unless the scene moved at least this far in the
#: image between them (pixels, :func:`scene_motion`) ...
_MOTION_MIN_PX = 3.0
#: ... nor a contrast unless it has this many centres in both frames, in this many pairs.
_MOTION_MIN_POINTS = 8
_MOTION_MIN_PAIRS = 3


def scene_motion(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The scene's image motion from frame ``a`` to frame ``b`` (pixels ``(du, dv)``):
    OpenCV's phase correlation of their grey images (Hanning-windowed), one translation
    for the whole frame, which the scene's texture dominates (a laser stripe is a few
    pixels of it)."""
    import cv2

    def grey(x: np.ndarray) -> np.ndarray:
        x = _check_image(np.asarray(x))
        x = x.mean(axis=2) if x.ndim == 3 else x
        return np.ascontiguousarray(x, dtype=np.float32)

    ga, gb = grey(a), grey(b)
    if ga.shape != gb.shape:
        raise ValueError(f"frames of different sizes: {ga.shape} and {gb.shape}")
    if min(ga.shape) < 8:
        return np.zeros(2)
    win = cv2.createHanningWindow((ga.shape[1], ga.shape[0]), cv2.CV_32F)
    (du, dv), _ = cv2.phaseCorrelate(ga, gb, win)
    return np.array([du, dv], dtype=np.float64)


def _nearest_px(points: np.ndarray, targets: np.ndarray, shape: tuple[int, int]
                ) -> np.ndarray:
    """Each of ``points`` (N, 2) (u, v)'s distance to the nearest of ``targets`` (M, 2),
    pixels; NaN for a point outside the ``shape`` (H, W) image (its partner is not seen)."""
    from scipy.spatial import cKDTree

    h, w = shape
    out = np.full(len(points), np.nan)
    inside = ((points[:, 0] > -0.5) & (points[:, 0] < w - 0.5) & (points[:, 1] > -0.5)
              & (points[:, 1] < h - 0.5))
    if inside.any() and len(targets):
        out[inside] = cKDTree(targets).query(points[inside])[0]
    return out


def laser_colour_by_motion(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]], scores: Mapping[str, float],
    colour: str, *, rois: Sequence[tuple[np.ndarray | None, np.ndarray | None]] | None = None,
    axes: Sequence[str | None] | None = None, options: StripeOptions = StripeOptions(),
    motions: Sequence[np.ndarray] | None = None,
) -> tuple[str | None, dict[str, Any]]:
    """The laser's colour as the contrast whose ridges move with the camera, not with the
    scene: the check of a contested colour (:func:`laser_colour_contested`,
    :func:`lightness_contested`) when the recording has no views to show the scene without
    the laser (:func:`laser_colour_beyond_scene`).

    The laser is rigid with the camera (the format's ``flange -> laser`` or ``camera ->
    laser`` is static): between two frames of a sweep its stripe moves in the image only
    as the surface's depth under it changes, while a texture's ridges move with the scene
    (the robot carries the camera past the object, or a turntable turns it). Per pair of
    frames of one sweep, the scene's image motion is one translation
    (:func:`scene_motion`); each candidate contrast's centres in the first frame
    (:func:`extract_stripe_centres` with that colour) are matched to the second frame's,
    as they are ("static") and shifted by the scene's motion ("flowed"): the median
    distance to the nearest centre, each. A contrast whose static distance (the median
    over the pairs) is at most :data:`_MOTION_NEAR_PX` and 1 / :data:`_MOTION_RATIO` of
    its flowed one moves with the camera; one whose static distance is more than that and
    its flowed one at most 1 / :data:`_MOTION_RATIO` of it, with the scene (a texture's
    flow is only roughly one translation: its flowed distance is not near zero); neither,
    where the scene moved along the stripe (both distances small). The vote's colour
    gives way only to a colour that moves with the camera where its own centres do not
    (a static distance at least :data:`_MOTION_RATIO` times larger); the lightness also
    where it moves with the camera (it holds the laser's light with the texture's: random
    scene 376, a green laser, lightness 1.9 px / 4.0 px, green 0.7 / 5.5 px). Pairs where the scene
    moved less than :data:`_MOTION_MIN_PX` tell nothing and are left out. Random scene 148
    (a blue laser on an orange checker body, no views; the vote red 683, blue 347): red
    static 6.3 px, flowed 1.3 px (the checker's edges); blue 0.8 px and 4.9 px (the
    laser).

    Parameters
    ----------
    pairs : sequence of (image, image)
        Pairs of laser frames of one sweep each, a few frames apart.
    scores : mapping of str to float
        :func:`estimate_laser_colour`'s scores; the candidates are the contrasts that
        scored, the lightness only when ``colour`` is the lightness.
    colour : str
        The vote's colour.
    rois : sequence of (roi, roi), optional
        Each pair's regions of interest (see :func:`extract_stripe_centres`).
    axes : sequence of {"columns", "rows", None}, optional
        Each pair's scan axis where the laser's geometry fixes it.
    options : StripeOptions
        The detector's options (the colour and axis are set per candidate and pair).
    motions : sequence of (2,) arrays, optional
        Each pair's :func:`scene_motion`, when the caller has it; else measured here.

    Returns
    -------
    colour : str or None
        The best scoring candidate that moves with the camera where the vote's
        ``colour`` does not; None otherwise (nothing to change).
    detail : dict
        ``pairs`` (used), ``scene_motion_px`` (median), and per candidate
        (``contrasts``) ``static_px``, ``flowed_px``, ``pairs`` and ``moves_with``
        (``"camera"``, ``"scene"`` or None).
    """
    rois = [(None, None)] * len(pairs) if rois is None else list(rois)
    axes = [None] * len(pairs) if axes is None else list(axes)
    motion = ([scene_motion(a, b) for a, b in pairs] if motions is None
              else [np.asarray(m, dtype=np.float64) for m in motions])
    if not (len(rois) == len(axes) == len(motion) == len(pairs)):
        raise ValueError(f"need one roi pair, one axis and one motion per pair, got "
                         f"{len(rois)}, {len(axes)} and {len(motion)} for {len(pairs)} pairs")
    cands = [c for c in CONTRASTS[:3] if float(scores.get(c, 0.0)) > 0]
    if colour == "lightness":
        cands.append("lightness")
    elif colour not in cands:
        cands.insert(0, colour)
    used = [k for k, m in enumerate(motion) if float(np.hypot(*m)) >= _MOTION_MIN_PX]
    detail: dict[str, Any] = {
        "pairs": len(used),
        "scene_motion_px": (round(float(np.median([np.hypot(*motion[k]) for k in used])), 2)
                            if used else None),
        "contrasts": {}}
    for c in cands:
        static, flowed = [], []
        for k in used:
            (a, b), (ra, rb) = pairs[k], rois[k]
            opt = options.replace(colour=c, axis=axes[k] or options.axis)
            pa = extract_stripe_centres(a, roi=ra, options=opt)
            pb = extract_stripe_centres(b, roi=rb, options=opt)
            if len(pa.u) < _MOTION_MIN_POINTS or len(pb.u) < _MOTION_MIN_POINTS:
                continue
            shape = np.asarray(a).shape[:2]
            pts, tgt = np.stack([pa.u, pa.v], 1), np.stack([pb.u, pb.v], 1)
            d0 = _nearest_px(pts, tgt, shape)
            d1 = _nearest_px(pts + motion[k], tgt, shape)
            if np.isfinite(d0).any() and np.isfinite(d1).any():
                static.append(float(np.nanmedian(d0)))
                flowed.append(float(np.nanmedian(d1)))
        entry: dict[str, Any] = {"pairs": len(static), "static_px": None, "flowed_px": None,
                                 "moves_with": None}
        if len(static) >= _MOTION_MIN_PAIRS:
            s0, s1 = float(np.median(static)), float(np.median(flowed))
            entry.update(static_px=round(s0, 2), flowed_px=round(s1, 2))
            if s0 <= _MOTION_NEAR_PX and s0 * _MOTION_RATIO <= s1:
                entry["moves_with"] = "camera"
            elif s0 > _MOTION_NEAR_PX and s1 * _MOTION_RATIO <= s0:
                entry["moves_with"] = "scene"
        detail["contrasts"][c] = entry
    won = detail["contrasts"].get(colour, {})
    # the lightness holds every colour's light: it stays with the camera wherever a
    # coloured laser does, so there only a colour that stays put closer takes its place
    if won.get("static_px") is None or (won["moves_with"] == "camera"
                                        and colour != "lightness"):
        return None, detail
    # a colour whose centres stay where the vote's do not
    with_camera = [c for c in cands if c != colour
                   and detail["contrasts"][c]["moves_with"] == "camera"
                   and detail["contrasts"][c]["static_px"] * _MOTION_RATIO <= won["static_px"]]
    if not with_camera:
        return None, detail
    return max(with_camera, key=lambda c: float(scores.get(c, 0.0))), detail


def extract_stripes_batch(
    frames: np.ndarray | Sequence[np.ndarray], *, threads: int = 1,
    options: StripeOptions = StripeOptions(),
) -> list[StripePoints]:
    """:func:`extract_stripe_centres` on every frame of a batch, on ``threads`` threads.

    Parameters
    ----------
    frames : (F, H, W) or (F, H, W, 3) array, or a sequence of (H, W[, 3]) arrays
        The laser-lit frames.
    threads : int
        Frames processed in parallel (the kernels release the GIL); 1 for none.
    options : StripeOptions
        As for :func:`extract_stripe_centres` (``s`` applies to every frame; when None
        each frame gets its own brightness coefficient).

    Returns
    -------
    list of StripePoints
        One per frame, in order.
    """
    if isinstance(frames, np.ndarray):
        if frames.ndim not in (3, 4) or (frames.ndim == 3 and frames.shape[2] == 3):
            raise ValueError(f"frames must be (F, H, W) or (F, H, W, 3) (a single RGB "
                             f"image is not a batch), got shape {frames.shape}")
    if int(threads) < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")

    def one(f: np.ndarray) -> StripePoints:
        return extract_stripe_centres(f, options=options)

    if int(threads) == 1 or len(frames) < 2:
        return [one(f) for f in frames]
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=int(threads)) as pool:
        return list(pool.map(one, frames))
