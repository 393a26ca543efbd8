"""The benchmark suite's machinery (benchmarks/suite.py, ``bsc bench``) on a tiny budget.

Not the figures themselves (the machine is shared; see ``python -m benchmarks``): that every
row has the common shape, that anchors and ratios are measured and positive, that an absent
benchmark module is a row saying so, and that ``bsc bench --json`` prints one JSON document.
"""
from __future__ import annotations

import json
import subprocess
import sys

import pytest

from benchmarks import anchors, suite

KEYS = {"group", "name", "value", "unit", "target", "ok", "anchor", "ratio"}


def test_suite_rows_anchors_and_ratios():
    doc = suite.run(quick=True, only=["numpy_matmul", "can_virtual", "zenoh_rtt", "drivers"])
    assert not doc["errors"], doc["errors"]
    rows = doc["rows"]
    for r in rows:
        assert KEYS <= set(r), r
    by_anchor = {r["name"]: r for r in rows if r["group"] == "anchor"}
    # drivers' rows are anchored on cantools' decode: measured on demand, shown with the others
    assert set(by_anchor) == {"cantools_decode", "zenoh_rtt", "can_virtual", "numpy_matmul"}
    for r in by_anchor.values():
        assert r["value"] > 0 and r["unit"] == anchors.ANCHORS[r["name"]][0]
    drivers = [r for r in rows if r["group"] == "drivers"]
    assert len(drivers) == 3
    for r in drivers:
        assert r["value"] > 0 and r["anchor"] == "cantools_decode"
        assert r["ratio"] == pytest.approx(r["value"] / by_anchor["cantools_decode"]["value"])
        assert isinstance(r["ok"], bool) and r["target"]
    assert doc["machine"]["cores"] >= 1 and doc["machine"]["load_start"] is not None
    json.dumps(doc)                                    # JSON-able as it is

    text = suite.table(doc)
    lines = text.splitlines()
    head = next(i for i, ln in enumerate(lines) if ln.startswith("group"))
    assert lines[head].split() == ["group", "figure", "value", "unit", "anchor", "ratio", "target", "ok"]
    assert "load average" in text and "numpy" in text and "batch decode" in text
    md = suite.table(doc, markdown=True, notes=False)
    assert "| group | figure |" in md and "| drivers | batch decode" in md


def test_absent_or_broken_benchmark_is_a_row(monkeypatch):
    monkeypatch.setitem(suite.BENCHMARKS, "ghost", ("benchmarks.bench_ghost", "a ghost", True))
    rows = suite.run_group("ghost", quick=True)
    assert len(rows) == 1 and rows[0]["value"] is None
    assert "benchmarks/bench_ghost.py does not exist" in rows[0]["note"]
    # a foreign module's row without anchor key / with NaN is normalised, not trusted
    r = suite.normalise("latency", {"name": "x", "value": float("nan"), "unit": "%"})
    assert KEYS <= set(r) and r["value"] is None and r["anchor"] is None and r["ratio"] is None
    with pytest.raises(ValueError, match="unknown benchmark"):
        suite.selection(["nope"], fuzz=False)
    assert "fuzz" not in suite.selection(None, fuzz=False)[1]
    assert "fuzz" in suite.selection(None, fuzz=True)[1]
    # the 60 s whole-system run needs root and a minute: only when named
    assert "capacity" not in suite.selection(None, fuzz=True)[1]
    assert suite.selection(["capacity"], fuzz=False)[1] == ["capacity"]


def test_bsc_bench_json():
    r = subprocess.run([sys.executable, "-m", "gateway.cli", "bench", "--quick", "--json", "-q",
                        "--only", "numpy_matmul"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    doc = json.loads(r.stdout)
    assert [x["name"] for x in doc["rows"]] == ["numpy_matmul"]
    assert doc["rows"][0]["value"] > 0 and doc["machine"]["versions"]["numpy"]


def test_every_name_a_benchmark_imports_exists():
    """A benchmark imports most of what it times inside its functions, where a module or a name
    that moved surfaces only as a failed row of ``bsc bench``: every ``from X import Y`` of the
    benchmarks, wherever it stands, must resolve."""
    import ast
    import importlib
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    missing = []
    for path in sorted((root / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 \
                    and node.module.split(".")[0] in ("gateway", "drivers", "simulator", "harness", "benchmarks",
                                                      "robot_description"):
                mod = importlib.import_module(node.module)
                for alias in node.names:
                    if not hasattr(mod, alias.name):
                        try:
                            importlib.import_module(f"{node.module}.{alias.name}")
                        except ImportError:
                            missing.append(f"{path.name}:{node.lineno}: {node.module}.{alias.name}")
    assert missing == [], missing


def test_the_accuracy_study_rows():
    """bench_accuracy (issue 17's study): per robot the worst joint of each of the four estimates,
    finite, in %; the gateway's (the joint filter) judged against 2 %."""
    from benchmarks import bench_accuracy

    rows = bench_accuracy.figures(quick=True)
    assert len(rows) == 8 and all(r["unit"] == "% NRMSE" and 0 <= r["value"] < 100 for r in rows)
    assert [r["target"] for r in rows if r["target"]] == ["<= 2 %"] * 2
    assert {r["name"].split(":")[0] for r in rows} == {"capture", "three_arm"}
