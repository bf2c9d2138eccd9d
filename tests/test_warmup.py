"""``robo3d warm-up`` (:mod:`robo3d.warmup`): the kernels it compiles are the ones a laser
frame's detection and the carver use, so that jobs started afterwards load them."""

from __future__ import annotations

import numpy as np

from robo3d.cli import main


def test_warm_up_compiles_the_detector_and_carver_kernels_for_8_bit_frames():
    from robo3d import octree, stripes
    from robo3d.warmup import compile_kernels

    t = compile_kernels(processes=1)  # in this process: its dispatchers are inspected
    assert set(t) == {"stripes", "carver", "geometry", "total"}
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


def _signatures() -> dict[str, int]:
    from numba.core.registry import CPUDispatcher

    from robo3d import registration, stripes, triangulation

    return {f"{m.__name__}.{k}": len(v.signatures) for m in (stripes, registration,
                                                             triangulation)
            for k, v in vars(m).items() if isinstance(v, CPUDispatcher)}


def test_the_stages_calls_need_no_compilation_after_the_warm_up():
    """As the stripes stage calls the detector (a raw monochrome frame, read-only over
    the message's bytes; the workspace's region; the axis and colour fixed) and as the
    triangulate and align stages call their kernels: nothing new to compile. Before,
    the warm-up covered the detector's defaults only, and the first monochrome cell
    recording compiled 12 kernels again (36 s of its first frame)."""
    from robo3d import stripes
    from robo3d.sim.rig import default_camera, default_laser_mount
    from robo3d.triangulation import triangulate_pixels
    from robo3d.warmup import compile_kernels, tiny_stripe_frame

    compile_kernels(processes=1)
    before = _signatures()
    assert before["robo3d.registration._rim_front"] and before[
        "robo3d.triangulation._ray_plane_kernel"]
    raw = np.frombuffer(np.kron(tiny_stripe_frame(), np.ones((4, 4), np.uint8)).tobytes(),
                        np.uint8).reshape(192, 256)
    assert not raw.flags.writeable
    roi = np.zeros(raw.shape, bool)
    roi[20:170, 10:240] = True
    for colour in ("auto", "lightness"):
        sp = stripes.extract_stripe_centres(raw, roi=roi, options=stripes.StripeOptions(
            axis="columns", colour=colour))
        assert len(sp) > 50
    rgb = np.stack([raw, np.full_like(raw, 10), np.full_like(raw, 10)], axis=-1)
    stripes.extract_stripe_centres(rgb, roi=roi, options=stripes.StripeOptions(
        axis="rows", colour="red", centre_on="luma"))
    triangulate_pixels(sp.pixels_uv, default_camera(256, 192), default_laser_mount())
    after = _signatures()
    assert {k: v for k, v in after.items() if v != before.get(k)} == {}


def test_all_types_covers_deeper_and_float_frames_and_the_other_methods():
    """``--all-types`` (``./run.sh test`` uses it): 16-bit and float frames, the band
    detector, the Gaussian centre and a followed curve then compile nothing new."""
    from robo3d import stripes
    from robo3d.warmup import compile_kernels, tiny_stripe_frame

    t = compile_kernels(processes=1, all_types=True)
    assert t["stripes_deep"] > 0 and t["stripes_methods"] > 0
    before = _signatures()
    u8 = np.kron(tiny_stripe_frame(), np.ones((3, 3), np.uint8))
    rgb = np.stack([u8, np.full_like(u8, 10), np.full_like(u8, 10)], axis=-1)
    calls = [(u8.astype(np.float64) / 255.0, dict(method="gaussian", min_peak=0.04)),
             (u8.astype(np.uint16) * 257, dict(detector="band", min_peak=2570.0)),
             (rgb.astype(np.float32) / 255.0, dict(axis="columns", min_peak=0.02)),
             (np.ascontiguousarray(np.swapaxes(rgb, 0, 1)).astype(np.uint16) * 257,
              dict(colour="red", axis="rows", centre_on="laser", follow=True,
                   min_peak=1285.0))]
    for img, kw in calls:
        assert len(stripes.extract_stripe_centres(img, options=stripes.StripeOptions(**kw)))
    after = _signatures()
    assert {k: v for k, v in after.items() if v != before.get(k)} == {}


def test_warm_up_command(caplog):
    caplog.set_level("INFO")
    assert main(["warm-up", "--processes", "1"]) == 0
    assert "kernels compiled or loaded from the cache" in caplog.text
