"""Segmentation of real photographs (seed §3.2 made robust, issue 10), on the recordings in
``../shared/real`` (skipped when that folder is absent; the project stands alone).

- DTU scan 24 (Jensen et al., CVPR 2014): a red-brick model house with grey roofs on a
  bright table before a dark backdrop, larger than many frames, with the published
  hand-made masks attached (``ground_truth/silhouettes/NNN.png``): the default
  segmentation is scored against them (issue 10's target: mean IoU >= 0.97, worst view
  >= 0.93; ``benchmarks`` runs all 49 views, this test every 4th).
- Middlebury templeSparseRing (Seitz et al., CVPR 2006): a plaster temple on a dark cloth,
  no masks: the default (colour) segmentation must agree with the seed's grey threshold,
  which suits this dark backdrop, keep the gaps between the columns, and raise no QA
  flag; the wrong polarity (the cloth selected) must be flagged in the stage's outputs.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

REAL = Path(__file__).resolve().parents[2] / "shared" / "real"
DTU = REAL / "dtu_scan24.mcap"
TEMPLE = REAL / "middlebury_templeSparseRing.mcap"


def _need(p: Path):
    return pytest.mark.skipif(not p.exists(), reason=f"real recording {p} not present "
                              "(it lives in the shared folder, outside the project)")


def _iou(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.count_nonzero(a & b) / max(np.count_nonzero(a | b), 1))


@_need(DTU)
def test_dtu_scan24_masks_match_the_published_ones():
    from robo3d.silhouettes import score_recording_silhouettes

    r = score_recording_silhouettes(str(DTU), step=4)
    assert r["n_views"] == 49 and r["n_scored"] == 13
    assert r["iou_mean"] >= 0.97, r["iou"]
    assert r["iou_min"] >= 0.93, r["iou"]
    assert r["qa_flags"] == {}   # an object larger than the frame is not absurd


@_need(TEMPLE)
def test_temple_default_segmentation_and_qa_flags_in_the_outputs(tmp_path):
    from robo3d.config import load_config
    from robo3d.pipeline import stage_silhouettes
    from robo3d.stages.common import load_silhouettes

    out = {"npz": str(tmp_path / "s.npz"), "report": str(tmp_path / "s.json"),
           "rrd": str(tmp_path / "s.rrd")}
    report = stage_silhouettes({"recording": str(TEMPLE)}, out, load_config(), "temple")
    views = report["views"]
    assert len(views) == 16 and report["n_qa_flagged"] == 0
    assert report["qa_flagged_views"] == []
    for v in views:
        assert v["polarity"] == "auto" and v["background_sample"] == "outside roi"
        assert v["refined"] is True and v["qa"]["flags"] == []
        assert not v["touches_image_border"]
    sil = load_silhouettes(out["npz"])
    masks = sil["masks"]
    assert not sil["qa_flagged"].any()
    # the seed's grey threshold suits a dark backdrop: the colour segmentation agrees
    # (measured: mean 0.955, worst 0.898; where they differ, the colour masks keep the
    # temple's shaded undersides that the grey threshold drops, and leave out the lit
    # cloth fold beside it that the grey threshold takes; see the overlays)
    grey_out = {k: str(tmp_path / f"g.{k}") for k in ("npz", "report", "rrd")}
    cfg = load_config(overrides={"segmentation": {"polarity": "brighter", "grabcut": False}})
    stage_silhouettes({"recording": str(TEMPLE)}, grey_out, cfg, "temple")
    grey = load_silhouettes(grey_out["npz"])["masks"]
    ious = [_iou(a, b) for a, b in zip(masks, grey, strict=True)]
    assert np.mean(ious) >= 0.94 and min(ious) >= 0.88, ious
    # the columns leave see-through gaps: background enclosed by the temple's silhouette
    import cv2

    n_gaps = []
    for m in masks:
        n, labels, stats, _ = cv2.connectedComponentsWithStats((~m).view(np.uint8),
                                                               connectivity=4)
        border = set(labels[0]) | set(labels[-1]) | set(labels[:, 0]) | set(labels[:, -1])
        n_gaps.append(sum(1 for i in range(1, n) if i not in border
                          and stats[i, cv2.CC_STAT_AREA] > 0.02 * m.sum()))
    assert sum(g > 0 for g in n_gaps) >= 8, n_gaps
    # the wrong polarity selects the cloth: every view is flagged, in report and NPZ
    bad_out = {k: str(tmp_path / f"b.{k}") for k in ("npz", "report", "rrd")}
    cfg = load_config(overrides={"segmentation": {"polarity": "darker", "grabcut": False}})
    bad = stage_silhouettes({"recording": str(TEMPLE)}, bad_out, cfg, "temple")
    assert bad["n_qa_flagged"] == 16 and bad["qa_flagged_views"] == list(range(16))
    assert all("touches_all_sides" in v["qa"]["flags"] for v in bad["views"])
    assert load_silhouettes(bad_out["npz"])["qa_flagged"].all()
