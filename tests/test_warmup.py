"""``robo3d warm-up`` (:mod:`robo3d.warmup`): the kernels it compiles are the ones a laser
frame's detection and the carver use, so that jobs started afterwards load them."""

from __future__ import annotations

import numpy as np

from robo3d.cli import main


def test_warm_up_compiles_the_detector_and_carver_kernels_for_8_bit_frames():
    from robo3d import octree, stripes
    from robo3d.warmup import compile_kernels

    t = compile_kernels(processes=1)  # in this process: its dispatchers are inspected
    assert set(t) == {"stripes", "carver", "total"}
    assert all(v > 0 for v in t.values())
    # the 8-bit frame kernels of the ridge detector (RGB and mono) and the carver's
    for kernel in (stripes._ridge_frame8, octree._carve_roots):
        assert kernel.signatures, kernel
    assert any(str(a.dtype) == "uint8" for sig in stripes._ridge_frame8.signatures
               for a in sig if hasattr(a, "dtype"))
    # ... and a frame of the workflow's size then needs no new compilation
    before = len(stripes._ridge_frame8.signatures)
    frame = np.zeros((120, 160, 3), np.uint8)
    frame[60:62, :, 0] = 200
    sp = stripes.extract_stripe_centres(frame)
    assert len(sp) > 100
    assert len(stripes._ridge_frame8.signatures) == before


def test_warm_up_command(caplog):
    caplog.set_level("INFO")
    assert main(["warm-up", "--processes", "1"]) == 0
    assert "kernels compiled or loaded from the cache" in caplog.text
