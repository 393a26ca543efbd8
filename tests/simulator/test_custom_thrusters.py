"""[[thrusters.custom]] layouts: loading, row-by-row errors, a run as a user runs it, the estimator."""
from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from robot_description.thrusters import (DEFAULT_LAYOUT, DEFAULT_MAX_THRUST_N, ThrusterLayout,
                                         ThrusterLayoutError)
from simulator import scenario
from simulator.engine import Simulation
from simulator.scenario import ScenarioError


def _rows() -> list[dict]:
    """Sixteen thrusters on a 2 m ring: tangential pairs at four azimuths (the -tangent ones at
    80 N), axial pairs 0.9 m above and below; the upper ones' direction not a unit vector."""
    out = []
    for deg in (0, 90, 180, 270):
        a = math.radians(deg)
        p = [round(2.0 * math.cos(a), 12), round(2.0 * math.sin(a), 12), 0.0]
        t = [-math.sin(a), math.cos(a), 0.0]
        out.append({"pos_m": p, "dir": t})
        out.append({"pos_m": p, "dir": [-x for x in t], "max_thrust_n": 80.0})
    for deg in (0, 90, 180, 270):
        a = math.radians(deg)
        xy = [round(2.0 * math.cos(a), 12), round(2.0 * math.sin(a), 12)]
        out.append({"pos_m": xy + [0.9], "dir": [0.0, 0.0, -2.0]})
        out.append({"pos_m": xy + [-0.9], "dir": [0.0, 0.0, 1.0]})
    return out


def _toml(rows: list[dict], head: str = "", thrusters: str = "") -> str:
    text = head + "[thrusters]\nmisalign_deg = 0.0\n" + thrusters
    for row in rows:
        text += "[[thrusters.custom]]\n" + "".join(f"{k} = {v!r}\n" for k, v in row.items())
    return text


def _expected_B(rows: list[dict]) -> np.ndarray:
    """6 x N thrust -> wrench about C, written out from the rows (not by the layout code)."""
    cols = []
    for row in rows:
        d = np.array(row["dir"], dtype=float)
        d /= math.sqrt(float(d @ d))
        cols.append(np.concatenate([d, np.cross(row["pos_m"], d)]))
    return np.array(cols).T


@pytest.fixture
def custom_file(tmp_path):
    f = tmp_path / "ring16.toml"
    f.write_text(_toml(_rows(), "duration_s = 1.0\n"))
    return f


def test_custom_rows_are_the_simulated_layout(custom_file):
    sim = Simulation(scenario.load(custom_file))
    lay = sim.layout
    assert lay.n == 16
    assert np.array_equal(lay.pos_m, [r["pos_m"] for r in _rows()])
    assert np.allclose(lay.B, _expected_B(_rows()), rtol=0, atol=1e-15)
    assert lay.max_n.tolist() == [100.0, 80.0] * 4 + [100.0] * 8     # per row, else [thrusters] max_thrust_n
    assert sim.alloc.B.shape == (6, 16) and sim.pwpfm.f.shape == (16,) and sim.thr_err.B_actual.shape == (6, 16)


def test_the_scenario_text_gives_the_same_layout(custom_file):
    """What a log carries (the scenario's text) and a scenario file given as a layout file
    (bsc gateway --thrusters) give the layout the simulator flew."""
    flown = Simulation(scenario.load(custom_file)).layout
    for lay in (ThrusterLayout.from_scenario_text(custom_file.read_text()), ThrusterLayout.load(custom_file),
                ThrusterLayout.from_config(scenario.load(custom_file).cfg.thrusters)):
        assert np.array_equal(lay.B, flown.B) and np.array_equal(lay.max_n, flown.max_n)


def test_a_logged_layout_is_the_layout_bsc_gateway_loaded(custom_file, tmp_path):
    """bsc gateway --record --thrusters SPEC attaches ThrusterLayout.scenario_text(SPEC); a replay
    rebuilds the layout from it bit for bit (a [[thruster]] file, a scenario file, a name)."""
    rows = tmp_path / "rows.toml"
    rows.write_text("max_thrust_n = 90.0\n" + "".join(
        "[[thruster]]\n" + "".join(f"{k} = {v!r}\n" for k, v in row.items()) for row in _rows()))
    for spec in (rows, custom_file, "ring18"):
        loaded = ThrusterLayout.load(spec)
        again = ThrusterLayout.from_scenario_text(ThrusterLayout.scenario_text(spec))
        for a, b in ((loaded.pos_m, again.pos_m), (loaded.dir, again.dir), (loaded.max_n, again.max_n)):
            assert np.array_equal(a, b), spec
    assert ThrusterLayout.load(rows).max_n.tolist() == [90.0, 80.0] * 4 + [90.0] * 8
    assert ThrusterLayout.scenario_text(None) is None


def test_the_layout_defaults_are_the_scenario_defaults():
    """A log whose scenario says nothing of thrusters flew the default file's layout."""
    cfg = scenario.load().cfg.thrusters
    assert (cfg.layout, cfg.max_thrust_n) == (DEFAULT_LAYOUT, DEFAULT_MAX_THRUST_N)
    assert np.array_equal(ThrusterLayout.from_scenario_text("duration_s = 1.0\n").B, ThrusterLayout.named().B)


def _with(i: int, **changes) -> list[dict]:
    rows = _rows()
    for k, v in changes.items():
        if v is None:
            del rows[i][k]
        else:
            rows[i][k] = v
    return rows


@pytest.mark.parametrize("text, match", [
    ("[thrusters]\ncustom = 3\n", "scenario key 'thrusters.custom' must be an array of tables"),
    ("[thrusters]\ncustom = []\n", r"thrusters.custom: 0 rows; a layout has 1\.\.32 thrusters"),
    (_toml(_rows() * 3), r"thrusters.custom: 48 rows; a layout has 1\.\.32"),
    (_toml(_with(1, dir=None)), r"thrusters.custom\[1\]: missing key 'dir'"),
    (_toml(_with(0, position=[1.0, 0.0, 0.0])), r"thrusters.custom\[0\]: unknown key 'position'"),
    (_toml(_with(2, pos_m=[0.0, float("nan"), 0.0])), r"thrusters.custom\[2\]: pos_m must be 3 finite numbers"),
    (_toml(_with(2, pos_m=[1.0, 2.0])), r"thrusters.custom\[2\]: pos_m must be 3 finite numbers"),
    (_toml(_with(3, dir=[0.0, 0.0, 0.0])), r"thrusters.custom\[3\]: dir must be a non-zero vector"),
    (_toml(_with(3, dir=[float("inf"), 0.0, 0.0])), r"thrusters.custom\[3\]: dir must be a non-zero vector"),
    (_toml(_with(4, dir=["up", 0.0, 0.0])), r"thrusters.custom\[4\]: dir must be a non-zero vector"),
    (_toml(_with(5, max_thrust_n=-5.0)), r"thrusters.custom\[5\]: max_thrust_n must be a positive number of N, got -5"),
    (_toml(_with(5, max_thrust_n=float("nan"))), r"thrusters.custom\[5\]: max_thrust_n must be a positive number"),
    (_toml(_with(5, max_thrust_n=0)), r"thrusters.custom\[5\]: max_thrust_n must be a positive number"),
    (_toml(_rows()[:4]), "thrusters.custom: 4 thruster\\(s\\) cannot control the spacecraft's 6 degrees of freedom"),
    # the eight in-plane thrusters: nothing along z nor about x and y
    (_toml(_rows()[:8]), r"thrusters.custom: no combination of the 8 thrusters gives \+force z, -force z, "
                         r"\+moment x, -moment x, \+moment y, -moment y"),
    (_toml(_rows(), thrusters="layout = 'ring18'\n"),
     r"both layout = 'ring18' and \[\[thrusters.custom\]\] rows; give one"),
    ("[thrusters]\nlayout = 'ring12'\n", "unknown thruster layout 'ring12'"),
])
def test_bad_layouts_name_the_row_and_field(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError, match=match):
        scenario.load(f)


def test_a_layout_file_names_its_rows(tmp_path):
    f = tmp_path / "layout.toml"
    f.write_text("[[thruster]]\npos_m = [1.0, 0.0, 0.0]\ndir = [0.0, 0.0, 0.0]\n")
    with pytest.raises(ThrusterLayoutError, match=r"layout\.toml: thruster\[0\]: dir must be a non-zero vector"):
        ThrusterLayout.load(f)


def test_bsc_sim_flies_a_custom_layout(custom_file, tmp_path):
    out = tmp_path / "out"
    r = subprocess.run([sys.executable, "-m", "gateway.cli", "sim", "--scenario", str(custom_file), "--duration", "1",
                        "--out", str(out), "--quiet", "--no-plots", "--no-compare"],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert json.loads((out / "summary.json").read_text())["scenario"] == "ring16"
    with np.load(out / "truth.npz", allow_pickle=False) as z:
        thrust, act, valves = z["thrust"], z["thr_act"], z["valves"]
    assert thrust.shape == (1000, 16) and valves.shape == (1000, 16)
    assert valves.any(axis=0).sum() >= 2                      # the base controller fired them
    # without misalignment, the actual wrench is the rows' geometry times each thrust
    assert np.allclose(act, thrust @ _expected_B(_rows()).T, rtol=1e-12, atol=1e-9)


def test_the_estimator_believes_the_custom_layout(custom_file):
    """The demo's path (simulator -> firmware frames -> drivers + estimator): with the
    scenario's layout the thruster wrench is estimated; with another 16-thruster layout
    (ring18's first sixteen) it is not, so the layout really is what the estimator uses."""
    from harness import demo

    sc = scenario.load(custom_file, {"duration_s": 1.5})
    ring = ThrusterLayout.named()
    other = ThrusterLayout(ring.pos_m[:16], ring.dir[:16], ring.max_n[:16])
    nrmse = {}
    for name, layout in (("scenario", None), ("other", other)):
        trace, est, _ = demo.run_offline(sc, layout=layout)
        act = trace["thr_act"]
        good = np.isfinite(est.thrusters).all(axis=1)
        err = np.sqrt(np.mean((est.thrusters[good] - act[good]) ** 2, axis=0))
        peak = np.abs(act).max(axis=0)
        nrmse[name] = err[[1, 5]] / peak[[1, 5]]           # force y and moment z: the axes it flew
        assert good.sum() > 1000
    assert np.all(nrmse["scenario"] < 0.05), nrmse
    assert np.all(nrmse["other"] > 0.15), nrmse
