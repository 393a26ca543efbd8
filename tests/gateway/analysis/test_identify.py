"""Per-session identification on synthetic streams with known friction, efficiency and bias."""
from __future__ import annotations

import numpy as np
import pytest

from gateway.analysis.session import AnalysisError, analyze_session, fit_efficiency, fit_friction

from .synth import write_session


def test_fit_friction_recovers_coulomb_viscous_and_offset():
    rng = np.random.default_rng(1)
    v = rng.uniform(-0.5, 0.5, 5000)
    r = 120.0 * np.sign(v) + 8.0 * v + 4.0 + rng.normal(0, 3.0, v.size)
    fit = fit_friction(r, v, "arm0/j2")
    assert fit.identifiable
    assert fit.coulomb_nm == pytest.approx(120.0, abs=0.3)
    assert fit.viscous_nms == pytest.approx(8.0, abs=1.0)
    assert fit.offset_nm == pytest.approx(4.0, abs=0.3)


def test_fit_friction_one_direction_only_is_not_identifiable():
    v = np.linspace(0.1, 0.5, 1000)
    fit = fit_friction(100 * np.sign(v), v)
    assert not fit.identifiable and np.isnan(fit.coulomb_nm)


def test_fit_friction_ignores_breakaway_spikes():
    rng = np.random.default_rng(2)
    v = rng.uniform(-0.5, 0.5, 4000)
    r = 90.0 * np.sign(v) + rng.normal(0, 1.0, v.size)
    r[::100] += 400.0            # stiction breakaways
    assert fit_friction(r, v).coulomb_nm == pytest.approx(90.0, abs=0.5)


def test_fit_efficiency_and_weak_axis():
    rng = np.random.default_rng(3)
    cmd = rng.normal(0, 50, 3000)
    fit = fit_efficiency(0.7 * cmd + 3.0 + rng.normal(0, 1, cmd.size), cmd, "fx")
    assert fit.identifiable and fit.efficiency == pytest.approx(0.7, abs=0.01)
    assert fit.offset == pytest.approx(3, abs=0.2)
    weak = fit_efficiency(rng.normal(0, 1, 3000), rng.normal(0, 1, 3000), "mx")
    assert not weak.identifiable and np.isnan(weak.efficiency)


def test_session_from_log(tmp_path):
    coulomb = {"arm0/j1": 180.0, "arm0/j2": 130.0, "arm1/j1": 170.0, "arm1/j2": 90.0}
    p = write_session(tmp_path / "s.mcap", 4, coulomb=coulomb, efficiency=0.8, thr_offset=0.0)
    f = analyze_session(p)
    assert f.robot == "synthbot" and f.index == 4
    for j, fc in coulomb.items():
        assert f.joints[j].coulomb_nm == pytest.approx(fc, abs=1.0)
        assert abs(f.joints[j].offset_nm) < 1.0
    assert f.axes["fx"].efficiency == pytest.approx(0.8, abs=0.01)
    assert f.axes["mz"].efficiency == pytest.approx(0.8, abs=0.01)
    assert not f.axes["fz"].identifiable
    assert f.axes["fx"].quiet_samples > 100 and abs(f.axes["fx"].quiet_offset) < 1.0


def test_ft_bias_moves_offsets_not_coulomb(tmp_path):
    p = write_session(tmp_path / "b.mcap", 0, ft_bias={"arm0": 25.0}, thr_offset=20.0)
    f = analyze_session(p)
    assert f.joints["arm0/j1"].offset_nm == pytest.approx(25.0, abs=1.0)
    assert f.joints["arm0/j2"].offset_nm > 20.0
    assert f.joints["arm0/j2"].coulomb_nm == pytest.approx(90.0, abs=3.0)
    assert abs(f.joints["arm1/j1"].offset_nm) < 1.0
    assert f.axes["fx"].quiet_offset == pytest.approx(20.0, abs=1.0)


def test_contacts_are_counted_per_arm(tmp_path):
    """A contact on arm1 from message 1000 to 1400 (200 Hz: from its first message to its last,
    1.995 s), up to 30 N; arm0 none; another session with a shorter one. bsc analyze's text lists
    them per session."""
    from gateway import analysis
    from gateway.analysis.report import summary_text

    p = write_session(tmp_path / "c.mcap", 0, contact={"arm1": (1000, 1400, (0.0, 30.0, 0.0, 0.0, 0.0, 1.0))})
    f = analyze_session(p)
    assert f.contacts == {"arm1": {"count": 1, "seconds": pytest.approx(399 / 200), "max_force_n": 30.0}}
    q = write_session(tmp_path / "d.mcap", 1, contact={"arm1": (3000, 3100, (10.0, 0.0, 0.0, 0.0, 0.0, 0.0))})
    assert analyze_session(q).contacts["arm1"]["count"] == 1
    result, skipped = analysis.run([p, q], progress=False)
    assert not skipped
    text = summary_text(result)
    assert "c                      arm1       1 contact(s), 2.00 s in all, up to 30.0 N" in text, text
    assert "arm0" not in text.split("contacts (")[1].split("alerts")[0]


def test_not_a_log_and_no_efforts(tmp_path):
    bad = tmp_path / "x.mcap"
    bad.write_bytes(b"not mcap")
    with pytest.raises(AnalysisError):
        analyze_session(bad)
    from gateway.log.recorder import Recorder
    empty = tmp_path / "e.mcap"
    with Recorder(empty) as rec:
        rec.record("/other", {"a": 1}, 1)
    with pytest.raises(AnalysisError, match="no JointEfforts"):
        analyze_session(empty)
