"""The ``simplify`` stage: the fused mesh cleaned and simplified (:mod:`robo3d.simplify`), its
vertex provenance carried along.
"""

from __future__ import annotations

import time
from collections.abc import Mapping
from typing import Any

from ..atomic import write_json
from .common import log, stage_threads, summary
from .fuse import source_colors


def stage_simplify(inputs: Mapping[str, str], outputs: Mapping[str, str],
                   cfg: Mapping[str, Any], rec_name: str, threads: int | None = None
                   ) -> dict[str, Any]:
    """Clean the fused mesh (duplicates, zero-area faces, small floating components) and
    simplify it by quadric edge collapse to ``simplify.target_faces`` and/or within
    ``simplify.max_error_m``; the Hausdorff distance to the fused mesh must stay within
    ``simplify.hausdorff_tolerance_m`` (more faces are kept until it does), and the
    inferred surface (the fused mesh's ``source``: hull, filled) within
    ``simplify.inferred_tolerance_m``, or half the hull's voxel (``hull``: hull.npz) where
    that is more. Writes
    ``ply`` and, when given, ``stl`` / ``obj`` outputs. ``threads``: the job's, for the
    distance checks (the result does not depend on it)."""
    from scipy.spatial import cKDTree

    from ..fusion import MEASURED, source_area_fractions
    from ..grid import VoxelGrid
    from ..meshio import read_mesh, read_vertex_attributes, write_mesh
    from ..simplify import SimplifyOptions, clean_mesh, simplify_mesh, transfer_vertex_attributes
    from ..viz import log_mesh, log_report, rerun_log

    t0 = time.perf_counter()
    sc = cfg["simplify"]
    hull_voxel = None
    if inputs.get("hull"):  # the inferred surface is known no better than its voxel
        hull_voxel = VoxelGrid.load_npz(inputs["hull"]).voxel_size
    opts = SimplifyOptions.from_config(sc, seed=cfg["seed"], threads=stage_threads(threads),
                                       hull_voxel_m=hull_voxel)
    V, F = read_mesh(inputs["fused"])
    attrs_in = read_vertex_attributes(inputs["fused"])
    V0 = V
    V, F, clean_report = clean_mesh(V, F, options=opts)
    inferred = None  # surface no sensor measured is held to its own, looser bound
    tree = cKDTree(V0) if attrs_in and len(V0) else None  # asked twice: built once
    if "source" in attrs_in:
        inferred = transfer_vertex_attributes(V0, {"source": attrs_in["source"]}, V,
                                              tree=tree, threads=opts.threads)[
            "source"] != MEASURED
    V2, F2, simp_report = simplify_mesh(V, F, options=opts, inferred=inferred)
    haus = simp_report.get("hausdorff_max_m")
    if "hausdorff_measured_max_m" in simp_report:
        within = (simp_report["hausdorff_measured_max_m"] <= sc["hausdorff_tolerance_m"]
                  and simp_report["hausdorff_inferred_max_m"]
                  <= simp_report["inferred_error_m"])
    else:
        within = haus is None or haus <= sc["hausdorff_tolerance_m"]
    if not within:
        log.warning("simplified mesh departs %.3f mm from the fused one, more than the "
                    "tolerance %.3f mm (inferred surface: %s)", haus * 1e3,
                    sc["hausdorff_tolerance_m"] * 1e3,
                    f"{simp_report['inferred_error_m'] * 1e3:.3f} mm"
                    if simp_report.get("inferred_error_m") else "the same")
    report = {"clean": clean_report, **simp_report, "faces_in": len(F), "faces_out": len(F2),
              "hausdorff_tolerance_m": sc["hausdorff_tolerance_m"],
              "within_tolerance": bool(within),
              "exports": [k for k in ("ply", "stl", "obj") if outputs.get(k)],
              "export_unit": {"ply": "m", "stl": sc["export_unit"], "obj": sc["export_unit"]},
              "seconds": round(time.perf_counter() - t0, 3)}
    attrs = transfer_vertex_attributes(V0, attrs_in, V2, tree=tree, threads=opts.threads)
    if "source" in attrs:
        fractions = source_area_fractions(V2, F2, attrs["source"])
        report["source_area_fraction"] = fractions
        report["inferred_area_fraction"] = 1.0 - fractions["measured"]
    colours = source_colors(attrs["source"]) if "source" in attrs else None
    for key in ("ply", "stl", "obj"):
        if outputs.get(key):
            write_mesh(outputs[key], V2, F2, vertex_colors=colours if key == "ply" else None,
                       attributes=attrs if key == "ply" else None,
                       unit="m" if key == "ply" else sc["export_unit"])
    with rerun_log(outputs["rrd"], rec_name) as rr_stream:
        if colours is not None:  # by provenance: grey measured, orange hull, yellow filled
            log_mesh(rr_stream, "base/simplify/mesh", V2, F2, vertex_colors=colours)
        else:
            log_mesh(rr_stream, "base/simplify/mesh", V2, F2, albedo=[230, 200, 160, 255])
        log_report(rr_stream, "reports/simplify", report)
    write_json(outputs["report"], report)
    n_places = int(report.get("kept_places") or 0)
    kept = (f"; {report['kept_faces']} faces around {n_places} "
            f"place{'s' if n_places > 1 else ''} kept as fused (decimating them went beyond "
            "the tolerance)" if n_places else "")
    split = (f" (measured {report['hausdorff_measured_max_m'] * 1e3:.3f} mm, inferred "
             f"{report['hausdorff_inferred_max_m'] * 1e3:.3f} mm of "
             f"{report['inferred_error_m'] * 1e3:.1f})"
             if "hausdorff_measured_max_m" in report else "")
    summary.info("simplified %d -> %d faces, Hausdorff %.3f mm%s%s (%.1f s)", len(F),
                 len(F2), (haus or 0.0) * 1e3, split, kept, report["seconds"])
    return report
