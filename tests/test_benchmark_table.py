"""benchmarks/table.py: the table of every benchmark's results (issue 14 item 6) reads
each file's figures, targets and peers as written, says which targets are met, and the
ratio against the peer in the right direction."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _table():
    spec = importlib.util.spec_from_file_location("bench_table", REPO / "benchmarks" / "table.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules["bench_table"] = mod  # dataclasses look the module up while defining Row
    spec.loader.exec_module(mod)
    return mod


def _row(text: str, *needles: str) -> list[str]:
    for line in text.splitlines():
        if all(n in line for n in needles):
            return [c.strip() for c in line.strip("|").split("|")]
    raise AssertionError(f"no row with {needles} in:\n{text}")


def test_table_targets_and_peers(tmp_path: Path) -> None:
    t = _table()
    (tmp_path / "carving.json").write_text(json.dumps(
        {"octree_256_s": 0.1, "open3d_256_s": 12.0, "octree_512_s": 3.0, "open3d_512_s": 60.0,
         "date": "2026-12-02"}))
    (tmp_path / "front_end.json").write_text(json.dumps(
        {"stripe_recall_min": 0.9, "stripe_median_mm": {"red": 0.04, "blue": 0.06},
         "fps_ambient_1280x960": 1200.0,
         "targets": {"stripe_recall_min": ">= 0.95", "stripe_median_mm": "<= 0.05",
                     "fps_ambient_1280x960": ">= 1000.0"}}))
    (tmp_path / "pipeline.json").write_text(json.dumps(
        {"vase": {"completeness_0_5mm": 0.995, "end_to_end_s": 70.0},
         "targets": {"completeness_0_5mm": 0.99, "end_to_end_s": 60.0}}))
    text = t.build(tmp_path)
    r = _row(text, "`octree_256_s`")
    assert r[4] == "0.1" and r[7] == "yes" and r[9] == "120x"  # peer time / ours
    r = _row(text, "`octree_512_s`")
    assert r[7] == "**no**" and r[9] == "20x"  # 3 s misses < 2 s
    assert _row(text, "`stripe_recall_min`")[7] == "**no**"
    assert _row(text, "(red)", "`stripe_median_mm`")[7] == "yes"
    assert _row(text, "(blue)", "`stripe_median_mm`")[7] == "**no**"
    assert _row(text, "`fps_ambient_1280x960`")[7] == "yes"
    # a bare-number target: completeness is a lower bound, time an upper one
    r = _row(text, "pipeline vase", "`completeness_0_5mm`")
    assert r[6] == ">= 0.99" and r[7] == "yes"
    r = _row(text, "pipeline vase", "`end_to_end_s`")
    assert r[6] == "<= 60.0" and r[7] == "**no**"
    assert "carving: 2026-12-02" in text
    assert "Not measured yet:" in text and "laser" in text.split("Not measured yet:")[1]


def test_committed_results_build() -> None:
    """The committed results/*.json all read into the table (no file the table cannot
    read, every headline figure of ROWS present in its file)."""
    t = _table()
    text = t.build()
    for r in t.ROWS:
        path = REPO / "benchmarks" / "results" / f"{r.bench}.json"
        if path.exists():
            assert t._get(json.loads(path.read_text()), r.key) is not None, (r.bench, r.key)
            assert f"`{r.key}`" in text
