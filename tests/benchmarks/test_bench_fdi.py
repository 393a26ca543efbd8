"""The fault-detection benchmark's bookkeeping (benchmarks/bench_fdi.py) on made-up verdicts: the
family covers every thruster and fault type with onsets in range, and the summary counts what
the targets count (stuck closed judged only where the thruster was commanded, a late alarm is
not in time, wrong alarms and healthy false alarms counted). The figures themselves come from
``bsc bench --only fdi`` (minutes of simulation)."""
from __future__ import annotations

import math

import pytest

from benchmarks import bench_fdi, suite
from robot_description.thrusters import ThrusterLayout


def test_family_covers_every_thruster_and_fault():
    cases = bench_fdi.family()
    n = ThrusterLayout.named().n
    for fault in ("stuck_open", "stuck_closed"):
        got = [c for c in cases if c.fault == fault]
        assert sorted(c.thruster for c in got) == list(range(n))
        assert all(2.0 <= c.onset_s <= 4.0 and c.duration_s == pytest.approx(c.onset_s + 2.0) for c in got)
    for size in bench_fdi.LOSS_SIZES:
        got = [c for c in cases if c.fault == "loss" and c.factor == pytest.approx(1 - size)]
        assert sorted(c.thruster for c in got) == list(range(n))
        # the target is a loss named within 10 s of its onset: the session lasts that long
        assert all(c.duration_s == pytest.approx(c.onset_s + bench_fdi.LOSS_WINDOW_S) for c in got)
    for size in bench_fdi.LEAK_SIZES:
        got = [c for c in cases if c.fault == "leak" and c.factor == pytest.approx(size)]
        assert sorted(c.thruster for c in got) == list(range(n)) and all(2.0 <= c.onset_s <= 3.0 for c in got)
    healthy = [c for c in cases if c.fault is None]
    assert sorted({c.scenario for c in healthy}) == ["capture", "three_arm"] and len(healthy) == 2 * bench_fdi.N_HEALTHY
    assert len({c.seed for c in cases if c.scenario == "capture"}) == len([c for c in cases if c.scenario == "capture"])
    assert bench_fdi.family() == cases                  # seeded: the same family every run
    assert "fdi" in suite.BENCHMARKS and "fdi" not in suite.selection(None, fuzz=False)[1]


def _v(fault, thruster, *, named=True, delay=0.2, duty=0.5, false=0, factor=1.0, scenario="capture"):
    nan = float("nan")
    return {"case": {"scenario": scenario, "seed": 1, "duration_s": 5.0, "thruster": thruster, "fault": fault,
                     "onset_s": 3.0, "factor": factor},
            "alarms": [], "named": named, "delay_s": delay if named else nan, "theta": 0.9 if named else nan,
            "theta_true": 0.92, "commanded_duty": duty, "commanded_after": duty, "false_alarms": false,
            "nrmse_modelled": 0.04 if named else nan, "nrmse_published": 0.3 if named else nan}


def test_summary_counts_what_the_targets_count():
    vs = [_v("stuck_open", 0), _v("stuck_open", 1, delay=0.7), _v("stuck_open", 2, named=False, false=1),
          _v("stuck_closed", 0), _v("stuck_closed", 1, named=False, duty=0.0),
          _v("loss", 3, factor=0.85, delay=1.5), _v("loss", 4, factor=0.85, named=False, duty=0.0),
          _v("loss", 5, factor=0.85, named=False), _v("loss", 9, factor=0.85, delay=10.5),
          {**_v("loss", 6, factor=0.85, named=False), "theta_true": float("nan")},
          _v("leak", 7, factor=0.2, delay=0.8), _v("leak", 8, factor=0.2, named=False, false=1),
          _v(None, None, named=False, false=0), _v(None, None, named=False, false=2, scenario="three_arm")]
    s = bench_fdi.summarise(vs)
    so = s["stuck"]["stuck_open"]
    assert (so["judged"], so["named_in_time"], so["wrong_alarms"]) == (3, 1, 1)
    assert so["rate"] == pytest.approx(1 / 3) and so["not_named"] == [1, 2]
    sc = s["stuck"]["stuck_closed"]
    assert (sc["judged"], sc["named_in_time"], sc["never_commanded"]) == (1, 1, [1]) and sc["rate"] == 1.0
    loss = s["loss"]["0.15"]
    assert (loss["judged"], loss["named"], loss["missed"]) == (3, 1, [5, 9]) and loss["delay_max_s"] == 1.5
    assert s["per_thruster"]["3"]["smallest loss named"] == "15 %" and s["per_thruster"]["6"]["loss 15%"] == "-"
    leak = s["leak"]["0.20"]
    assert (leak["runs"], leak["named"], leak["missed"], leak["wrong_alarms"]) == (2, 1, [8], 1)
    assert s["per_thruster"]["7"]["leak 20%"] == "0.80 s" and s["per_thruster"]["8"]["leak 20%"] == "missed"
    assert s["healthy"] == {"capture": {"sessions": 1, "false_alarms": 0},
                            "three_arm": {"sessions": 1, "false_alarms": 2}}


def test_a_stuck_closed_valve_is_also_timed_from_its_first_command():
    late = {**_v("stuck_closed", 2, delay=0.64, duty=0.02), "commanded_from_s": 0.48}   # first fired at 0.48 s
    slow = {**_v("stuck_closed", 3, delay=0.9, duty=0.2), "commanded_from_s": 0.1}      # fired at once, named late
    old = _v("stuck_closed", 4, delay=0.3)                                              # no commanded_from_s
    sc = bench_fdi.summarise([late, slow, old])["stuck"]["stuck_closed"]
    assert (sc["judged"], sc["named_in_time"], sc["not_named"]) == (3, 1, [2, 3])      # from the onset
    assert sc["named_in_time_from_command"] == 2 and sc["rate_from_command"] == pytest.approx(2 / 3)
    assert sc["first_command_max_s"] == pytest.approx(0.48)
    opened = {**_v("stuck_open", 5, delay=0.7), "commanded_from_s": 0.4}               # shows at once: from the onset
    assert bench_fdi.summarise([opened])["stuck"]["stuck_open"]["named_in_time_from_command"] == 0


def test_early_family_covers_every_thruster_in_the_first_convergence():
    cases = bench_fdi.early_family()
    n = ThrusterLayout.named().n
    for fault in ("stuck_open", "stuck_closed"):
        got = [c for c in cases if c.fault == fault]
        assert sorted(c.thruster for c in got) == list(range(n))
        assert all(0.3 <= c.onset_s <= bench_fdi.EARLY_S and c.duration_s == pytest.approx(c.onset_s + 2.0)
                   for c in got)
    assert not {c.seed for c in cases} & {c.seed for c in bench_fdi.family()}
    assert bench_fdi.early_family() == cases


def test_early_onsets_are_summarised_apart():
    early = {**_v("stuck_open", 4, named=False), "case": {**_v("stuck_open", 4)["case"], "onset_s": 0.8}}
    s = bench_fdi.summarise([_v("stuck_open", 0), early])
    assert s["stuck"]["stuck_open"]["judged"] == 1 and s["stuck"]["stuck_open"]["rate"] == 1.0
    assert s["stuck"]["stuck_open early"]["judged"] == 1 and s["stuck"]["stuck_open early"]["rate"] == 0.0
    assert "stuck_closed early" not in s["stuck"] and "4" not in s["per_thruster"]


def test_run_takes_only_the_fault_types_asked_for(monkeypatch):
    import gateway.parallel

    seen = []
    monkeypatch.setattr(gateway.parallel, "map_jobs", lambda fn, jobs, **kw: seen.extend(j[0] for j in jobs) or [])
    bench_fdi.run(faults=["leak", "healthy"])
    assert {c.fault for c in seen} == {"leak", None}
    assert len(seen) == len(bench_fdi.LEAK_SIZES) * ThrusterLayout.named().n + 2 * bench_fdi.N_HEALTHY


def test_repeated_losses_have_their_own_onsets_and_seeds():
    cases = bench_fdi.loss_repeats(3, [0, 6], sizes=(0.1, 0.15))
    assert len(cases) == 3 * 2 * 2 and {c.fault for c in cases} == {"loss"} and {c.thruster for c in cases} == {0, 6}
    assert len({c.onset_s for c in cases}) == len(cases) and all(2.0 <= c.onset_s <= 3.0 for c in cases)
    assert all(c.duration_s == pytest.approx(c.onset_s + bench_fdi.LOSS_WINDOW_S) for c in cases)
    seeds = [c.seed for c in cases]
    assert len(set(seeds)) == len(seeds)
    assert not set(seeds) & {c.seed for c in bench_fdi.family() + bench_fdi.early_family()}


def test_the_rates_lower_bound_is_clopper_pearsons():
    assert bench_fdi.lower_bound(20, 20) == pytest.approx(0.05 ** (1 / 20), abs=1e-9)     # 0.861
    assert bench_fdi.lower_bound(59, 59) >= 0.95 > bench_fdi.lower_bound(58, 58)
    # 18 of 20: the p at which 18 or more is 5 % likely (a beta quantile; computed independently)
    p = bench_fdi.lower_bound(18, 20)
    assert sum(math.comb(20, i) * p ** i * (1 - p) ** (20 - i) for i in (18, 19, 20)) == pytest.approx(0.05, abs=1e-9)
    assert 0.71 < p < 0.72 and bench_fdi.lower_bound(0, 5) == 0.0 and math.isnan(bench_fdi.lower_bound(0, 0))


def test_loss_rates_per_thruster_count_every_run_and_the_table_keeps_the_first():
    vs = [_v("loss", 3, factor=0.9, delay=1.0), _v("loss", 3, factor=0.9, named=False),
          _v("loss", 3, factor=0.9, delay=11.0), _v("loss", 3, factor=0.9, named=False, duty=0.0),
          {**_v("loss", 3, factor=0.9, named=False), "theta_true": float("nan")}]
    s = bench_fdi.summarise(vs)
    # the last two were not judged (never commanded after the onset; never fired before it)
    assert s["loss_rate"]["3"]["0.10"] == {"named": 1, "judged": 3, "lower95": bench_fdi.lower_bound(1, 3)}
    assert s["loss"]["0.10"]["judged"] == 3 and s["per_thruster"]["3"]["loss 10%"] == "1.00 s"


def test_run_takes_repeated_losses_of_the_thrusters_asked_for(monkeypatch):
    import gateway.parallel

    seen = []
    monkeypatch.setattr(gateway.parallel, "map_jobs", lambda fn, jobs, **kw: seen.extend(j[0] for j in jobs) or [])
    bench_fdi.run(faults=["loss"], loss_runs=4, thrusters=[1, 2])
    assert {c.thruster for c in seen} == {1, 2} and {c.fault for c in seen} == {"loss"}
    assert len(seen) == 4 * 2 * len(bench_fdi.LOSS_SIZES)
    seen.clear()
    bench_fdi.run(faults=["loss"], loss_runs=3, thrusters=[0], loss_sizes=(0.15,))
    assert len(seen) == 3 and {round(1 - c.factor, 3) for c in seen} == {0.15}


def test_checkout_family_puts_every_fault_in_a_checkout():
    """``--scenario checkout``: the same faults, thrusters and onsets in checkout sessions, and the
    healthy sessions are checkouts as long as a loss's (the false alarms counted for them)."""
    capture, checkout = bench_fdi.family(), bench_fdi.family(scenario="checkout")
    faults = [c for c in checkout if c.fault is not None]
    assert {c.scenario for c in faults} == {"checkout"}
    assert [(c.fault, c.thruster, round(c.onset_s - 3.0, 3), c.factor) for c in faults] == \
        [(c.fault, c.thruster, c.onset_s, c.factor) for c in capture if c.fault is not None]
    healthy = [c for c in checkout if c.fault is None]
    assert len(healthy) == bench_fdi.N_HEALTHY and {c.scenario for c in healthy} == {"checkout"}
    assert all(c.duration_s == pytest.approx(6.0 + bench_fdi.LOSS_WINDOW_S) for c in healthy)
    assert {c.scenario for c in bench_fdi.loss_repeats(2, [0], (0.15,), scenario="checkout")} == {"checkout"}
    s = bench_fdi.summarise([_v(None, None, named=False, false=1, scenario="checkout")])
    assert s["healthy"]["checkout"] == {"sessions": 1, "false_alarms": 1}
    assert s["healthy"]["capture"] == {"sessions": 0, "false_alarms": 0}
