"""Rules file parsing and the hysteresis / hold-time state machine."""
from __future__ import annotations

import pytest

from gateway.monitor.rules import DEFAULT_RULES, Rule, RuleEngine, RulesError, load_rules

S = 1_000_000_000


def test_default_rules_load():
    rs = load_rules()
    assert rs.path == str(DEFAULT_RULES)
    names = {r.name for r in rs.rules}
    assert {"joint-friction-high", "thruster-efficiency-low", "sensor-stale", "bus-load-high"} <= names
    assert {d.metric for d in rs.detectors} == {"coulomb_nm", "efficiency", "offset_nm", "quiet_offset",
                                                "ft_bias_n", "ft_bias_nm"}


@pytest.mark.parametrize("body, match", [
    ('[[rule]]\nname="a"\nkind="actuator"\nmetric="friction_nm"\nraise=1\n', "missing key 'clear'"),
    ('[[rule]]\nname="a"\nkind="motor"\nmetric="friction_nm"\nraise=1\nclear=0\n', "kind must be"),
    ('[[rule]]\nname="a"\nkind="actuator"\nmetric="nope"\nraise=1\nclear=0\n', "metric must be"),
    ('[[rule]]\nname="a"\nkind="actuator"\nmetric="friction_nm"\nraise=1\nclear=2\n', "hysteresis"),
    ('[[rule]]\nname="a"\nkind="actuator"\nmetric="friction_nm"\nraise=1\nclear=0\ntypo=3\n', "unknown key 'typo'"),
    ('[monitor]\ntau_s = "x"\n', "wrong type"),
    ('[[analysis.detector]]\nname="d"\nmetric="coulomb_nm"\nkind="actuator"\ndirection="sideways"\n', "direction"),
    ("not toml [", "not valid TOML"),
])
def test_bad_rules_name_the_problem(tmp_path, body, match):
    p = tmp_path / "r.toml"
    p.write_text(body)
    with pytest.raises(RulesError, match=match):
        load_rules(p)


def test_missing_file():
    with pytest.raises(RulesError, match="no rules file"):
        load_rules("/nonexistent/rules.toml")


def rule(**kw):
    base = dict(name="r", kind="actuator", metric="friction_nm", raise_level=100.0, clear_level=80.0,
                hold_s=1.0, clear_hold_s=2.0, severity="critical")
    base.update(kw)
    return Rule(**base)


def drive(engine, values, dt_s=0.5):
    out = []
    for i, v in enumerate(values):
        out += [(i, a) for a in engine.update("bot", "actuator", "arm0/j2", "friction_nm", v, i * int(dt_s * S))]
    return out


def test_raise_after_hold_then_clear_after_clear_hold_with_hysteresis():
    eng = RuleEngine((rule(),))
    #        0    1    2    3    4    5    6   7   8   9   10  11
    vals = [50, 120, 120, 120, 90, 120, 90, 70, 70, 70, 70, 70]
    got = drive(eng, vals)
    assert [(i, a.state) for i, a in got] == [(3, "raised"), (11, "cleared")]
    raised = got[0][1]
    assert raised.since_ns == 1 * S // 2 and raised.t_ns == 3 * S // 2 and raised.severity == "critical"
    assert dict(raised.evidence)["friction_nm"] == 120 and dict(raised.evidence)["raise"] == 100
    assert got[1][1].severity == "info" and got[1][1].since_ns == raised.since_ns


def test_a_short_excursion_does_not_raise():
    eng = RuleEngine((rule(),))
    assert drive(eng, [50, 120, 50, 120, 50, 120, 50]) == []


def test_below_rules_and_target_globs():
    r = rule(kind="thruster", metric="efficiency", raise_level=0.75, clear_level=0.8, above=False, targets="f?",
             hold_s=0.0, clear_hold_s=0.0)
    eng = RuleEngine((r,))
    assert eng.update("bot", "thruster", "mz", "efficiency", 0.5, 0) == []
    assert eng.update("bot", "actuator", "fx", "efficiency", 0.5, 0) == []
    a = eng.update("bot", "thruster", "fx", "efficiency", 0.7, 1)
    assert [x.state for x in a] == ["raised"]
    assert eng.update("bot", "thruster", "fx", "efficiency", 0.78, 2) == []        # inside the hysteresis band
    assert [x.state for x in eng.update("bot", "thruster", "fx", "efficiency", 0.85, 3)] == ["cleared"]


def test_nan_keeps_state():
    eng = RuleEngine((rule(hold_s=0.0),))
    assert [a.state for a in eng.update("b", "actuator", "j", "friction_nm", 150.0, 0)] == ["raised"]
    assert eng.update("b", "actuator", "j", "friction_nm", float("nan"), 1) == []
    assert eng.active() == [("b", "r", "j")]
