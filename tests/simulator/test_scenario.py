"""Scenario files: defaults, validation, degradations."""
from __future__ import annotations

import numpy as np
import pytest

from simulator import scenario
from simulator.engine import Simulation
from simulator.scenario import ScenarioError


def test_defaults_are_the_capture_task():
    sc = scenario.load()
    assert sc.name == "capture" and sc.robot == "paper_robot"
    assert sc.cfg.target.spin_rpm == 3.0 and sc.cfg.target.radius_m == 3.0


@pytest.mark.parametrize("text, match", [
    ("durtion_s = 3\n", "unknown scenario key 'durtion_s'"),
    ("[noise.ft]\nforce_noise_n = 'big'\n", "noise.ft.force_noise_n"),
    ("[[degrade]]\nkind = 'gremlins'\n", "kind must be one of"),
    ("[[degrade]]\nkind = 'thruster_loss'\nthruster = 1\n", "missing key 'onset_s'"),
    ("duration_s = [\n", "not valid TOML"),
])
def test_bad_files_name_the_problem(tmp_path, text, match):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ScenarioError, match=match):
        scenario.load(f)


def test_partial_file_merges_over_defaults(tmp_path):
    f = tmp_path / "short.toml"
    f.write_text("duration_s = 0.5\n[friction]\ncoulomb_fraction = 0.45\n")
    sc = scenario.load(f)
    assert sc.duration_s == 0.5 and sc.cfg.friction.coulomb_fraction == 0.45
    assert sc.cfg.noise.imu.rate_hz == 500           # untouched default


def test_degradations_act_at_their_onset():
    sc = scenario.load("capture", {"duration_s": 0.6})
    data = dict(sc.data)
    data["degrade"] = [
        {"kind": "friction_growth", "joint": "arm0/j2", "onset_s": 0.2, "to_fraction": 0.6, "ramp_s": 0.2},
        {"kind": "thruster_stuck", "thruster": 3, "onset_s": 0.3, "state": "open"},
        {"kind": "ft_bias_drift", "arm": "arm1", "onset_s": 0.1, "force_n_per_s": [10.0, 0, 0],
         "torque_nm_per_s": [0, 0, 0]},
    ]
    sim = Simulation(scenario._build(sc.name, sc.text, data))
    tr = sim.run()
    assert sim.dyn.friction.coulomb_nm[1] == pytest.approx(0.6 * sim.robot.effort_limit[1])
    assert tr["valves"][350:, 3].all() and not tr["valves"][:100, 3].all()
    bias = tr["ft_meas"][:, 1, 0] - tr["ft_true"][:, 1, 0]
    assert bias[550:].mean() - bias[:90].mean() == pytest.approx(10.0 * 0.5, abs=0.3)
