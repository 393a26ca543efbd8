"""The closed inner loop, in lockstep: the simulated robot's joint drives take their commands from
the compensator (:class:`gateway.control.JointCompensator`) fed by the gateway's session engine on
the firmware's own frames.

Per 1 ms step: the simulator steps (its flight software computes the desired torques, the drives
apply the latest command they were given), the sensor firmware encodes the step's frames, the
session decodes them and estimates the efforts; the compensator sees the desired torques the arm
bus carried (``TorqueCommand`` samples, every 2 ms) and the estimates, and each completed set of
desired torques becomes the drives' command for the following steps. The correction is therefore
one step late, as it would be through the wire, and the run is deterministic. The thruster loop
(:class:`gateway.control.ThrusterCompensator`) likewise: it sees the commanded wrench the spacecraft
bus carried (``ThrusterCommand``), the thruster filter's learned per-valve wrenches with the
quality of the same epoch's thruster efforts, as the gateway publishes them
(``bsc/<robot>/efforts/valves``, every 5 ms), and the fault detector's alerts, and commands the
valves of the next step.

:func:`closed_loop_study` runs the scenario three ways (no friction; friction, open loop; friction,
compensated) and returns the figures of ``report.json``'s ``closed_loop`` block.
"""
from __future__ import annotations

import numpy as np

from drivers.samples import ThrusterCommand, TorqueCommand
from gateway.control import JointCompensator, JointLoopSettings, ThrusterCompensator, ThrusterLoopSettings
from gateway.efforts import Alert, JointEfforts, ValveWrenches


def run_compensated(scenario, *, settings: JointLoopSettings | None = None, enabled: bool = True,
                    command_limit: float = 1.0, thrust_limit: float = 1.0, faults=None, progress: bool = False,
                    thrusters: bool = True,
                    thruster_settings: ThrusterLoopSettings | None = None, thrusters_enabled: bool | None = None,
                    valve_delay_steps=None, valve_max_age_steps: int | None = None):
    """Simulator -> firmware frames -> session -> compensator -> the simulator's drives (and,
    with ``thrusters``, its valves), in lockstep in this thread. ``faults``: the firmware's fault
    injection (:class:`simulator.firmware.Faults`). ``thrusters_enabled`` (default ``enabled``):
    False runs the thruster loop on the nominal wrenches. Returns (trace, info): ``info`` counts
    the commands issued closed and open per arm and the flags they carried, lists the loop's
    transitions, and ``closed`` (N, p) says per step whether each arm's drives were under a
    closed-loop command, ``applied`` (N, n) is the command the drives applied, N m; ``thrusters``
    the same for the valves (``closed`` (N,): the step's valves came from the learned wrenches).

    ``valve_delay_steps`` (None: the valves of each step, computed just before it): the valves as
    ``bsc control`` sends them, a schedule per commanded wrench (10 steps and a look-ahead of 10:
    :meth:`ThrusterCompensator.schedule`), each given to the robot that many steps after the step
    that carried the commanded wrench (an int, or one per schedule, cycled): the real-time loop's
    delay, deterministic (rows for steps already run are lost, as on the robot). A schedule more
    than ``valve_max_age_steps`` late is dropped whole, as :class:`ValveInbox` drops one older
    than its ``max_age_s`` (counted in ``info["thrusters"]["too_old"]``)."""
    from gateway.engine import Session, Sink
    from robot_description.thrusters import ThrusterLayout
    from simulator.engine import Simulation
    from simulator.firmware import Firmware
    from simulator.progress import SimProgress

    from simulator.engine import DT_NS

    sim = Simulation(scenario, external_drives=True, command_limit=command_limit, external_thrusters=thrusters,
                     thrust_limit=thrust_limit)
    robot = sim.robot
    fw = Firmware(robot, faults=faults)
    comp = JointCompensator.for_robot(robot, settings, enabled=enabled)
    min_on = max(1, round(scenario.cfg.thrusters.pwpfm.min_on_s * 1e9 / DT_NS))
    thr = ThrusterCompensator.for_layout(sim.layout, min_on=min_on, settings=thruster_settings,
                                         enabled=enabled if thrusters_enabled is None else thrusters_enabled)
    bits = 1 << np.arange(sim.layout.n)
    thr_count = {"closed": 0, "open": 0}
    thr_flags: dict[str, int] = {}
    thr_closed = np.zeros(sim.n_steps, dtype=bool)
    have_demand = False
    names = list(robot.joint_names)
    cols = {a.name: [names.index(f"{a.name}/{j}") for j in a.joint_names] for a in robot.arms}
    ready: list[str] = []
    sent: list[int] = []                                # commanded wrenches answered with a schedule
    too_old: list[int] = []                             # schedules dropped by the robot's deadline
    fifo: list[int] = []                                # each schedule's arrival step
    delays = None if valve_delay_steps is None else np.atleast_1d(np.asarray(valve_delay_steps, dtype=np.int64))
    inbox: list[tuple] = []                             # (due step, rows, first step's t_ns, closed)

    class Feed(Sink):
        def emit(self, key, obj, log_ns) -> None:
            nonlocal have_demand
            if isinstance(obj, JointEfforts):
                comp.estimate(obj)
            elif isinstance(obj, TorqueCommand):
                arm = comp.observe(obj)
                if arm is not None:
                    ready.append(arm)
            elif not thrusters:
                return
            elif isinstance(obj, ValveWrenches):            # what the gateway publishes, 200 Hz
                thr.estimate(obj)
            elif isinstance(obj, ThrusterCommand):
                thr.observe(obj)                            # with the keep-out mask on the wire
                have_demand = True
                if delays is not None and (not sent or obj.t_ns > sent[-1]):
                    d = delays[len(sent) % len(delays)]
                    sent.append(obj.t_ns)
                    v = thr.schedule(obj.t_ns + DT_NS, 10, DT_NS, lookahead=10)
                    thr_count["closed" if v.closed else "open"] += 1        # here: schedules
                    # one link, in order: a schedule never overtakes the one before it
                    due = max(sim.k + int(d), fifo[-1] if fifo else 0)
                    fifo.append(due)
                    if valve_max_age_steps is not None and due - sim.k > valve_max_age_steps:
                        too_old.append(v.t_ns)
                        return
                    rows = (np.array(v.masks(), dtype=np.int64)[:, None] & bits) != 0
                    inbox.append((due, rows, v.t_ns, v.closed))
            elif isinstance(obj, Alert):
                thr.alert(obj)

    ses = Session(robot, [Feed()], samples=True, layout=ThrusterLayout.from_config(scenario.cfg.thrusters))
    counts = {a: {"closed": 0, "open": 0} for a in cols}
    flags: dict[str, int] = {}
    drive = None
    arm_ix = {a: i for i, a in enumerate(cols)}
    closed = np.zeros((sim.n_steps, len(cols)), dtype=bool)
    state = np.zeros(len(cols), dtype=bool)            # the mode of the command the drives hold
    feed = ses.feed
    with SimProgress(scenario.name + " (compensated)", sim.n_steps, 1e-3, enabled=progress) as bar:
        while sim.k < sim.n_steps:
            while inbox and inbox[0][0] <= sim.k:         # the schedules that reached the robot
                _, rows, t_first, is_closed = inbox.pop(0)
                sim.command_valves(rows, t_first)
                k0 = t_first // DT_NS
                thr_closed[max(k0, sim.k):k0 + len(rows)] = is_closed
            r = sim.step()
            for bus, msg in fw.frames(r):
                feed(bus, msg)
            if ready:
                if drive is None:
                    drive = sim.trace.arrays["tau_cmd"][sim.k - 1].copy()
                for arm in ready:
                    cmd = comp.command(arm, r.t_ns)
                    drive[cols[arm]] = cmd.torque_nm
                    counts[arm]["closed" if cmd.closed else "open"] += 1
                    state[arm_ix[arm]] = cmd.closed
                    for f in cmd.flags:
                        key = f.split(" ")[0]
                        flags[key] = flags.get(key, 0) + 1
                ready.clear()
                sim.command_drives(drive)
            if sim.k < sim.n_steps:
                closed[sim.k] = state               # the drives apply it from the next step on
                if have_demand and delays is None:      # the valves of the next step
                    v = thr.valves(r.t_ns + DT_NS)
                    sim.command_valves((v.valves & bits) != 0, v.t_ns)
                    thr_closed[sim.k] = v.closed
                    thr_count["closed" if v.closed else "open"] += 1
                    for f in v.flags:
                        key = f.split(" ")[0]
                        thr_flags[key] = thr_flags.get(key, 0) + 1
            bar.update(sim.k)
    ses.close()
    events = [{"arm": e.arm, "t_s": e.t_ns * 1e-9, "state": e.state, "reason": e.reason} for e in comp.events]
    thr_info = None
    if thrusters:
        thr_info = {"commands": thr_count, "flags": thr_flags,
                    "transitions": [{"t_s": e.t_ns * 1e-9, "state": e.state, "reason": e.reason} for e in thr.events],
                    "steps_external": int(sim.valves_external.sum()), "late": sim.valves_late,
                    "too_old": len(too_old),
                    "closed": thr_closed, "applied": sim.valves_applied}
    return sim.trace, {"commands": counts, "flags": flags, "transitions": events, "closed": closed,
                       "applied": sim.drive_applied, "thrusters": thr_info}


def ee_rms(trace, from_s: float = 0.0) -> dict:
    """RMS end-effector position error |actual - desired| per arm and overall (all arms' errors
    together), m, over the samples from ``from_s``."""
    A = trace.arrays
    keep = A["t_s"] >= from_s
    e = np.linalg.norm(A["ee"][keep] - A["ee_des"][keep], axis=2)          # (N, p)
    out = {arm: float(np.sqrt(np.mean(e[:, k] ** 2))) for k, arm in enumerate(trace.meta["arms"])}
    out["overall"] = float(np.sqrt(np.mean(e ** 2)))
    return out


def torque_rms(trace) -> dict:
    """RMS of actual minus desired joint torque (the flight software's command), N m, per joint
    and overall."""
    A = trace.arrays
    e = A["tau_act"] - A["tau_cmd"]
    out = {name: float(np.sqrt(np.mean(e[:, j] ** 2))) for j, name in enumerate(trace.meta["joints"])}
    out["overall"] = float(np.sqrt(np.mean(e ** 2)))
    return out


BAND_HZ = 20.0          # the thruster wrench's error is judged band-limited, as the estimator's (harness.demo)


def wrench_rms(trace, band_hz: float | None = BAND_HZ) -> dict:
    """RMS of the actual thruster wrench minus the one the flight software commanded (its
    allocation's wrench, what the spacecraft bus carries as the commanded wrench), force N and
    moment N m (vector norms over the three axes), band-limited to ``band_hz`` (zero-phase
    low-pass; None: raw at 1 kHz, where the valves' on/off pulses dominate); ``per_axis`` the
    RMS of each axis (fx fy fz N, mx my mz N m)."""
    from harness.demo import lowpass

    A = trace.arrays
    e = A["thr_act"] - A["thr_cmd"]
    if band_hz is not None:
        e = lowpass(e, band_hz)
    return {"force_n": float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1)))),
            "moment_nm": float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1)))),
            "per_axis": [round(float(x), 3) for x in np.sqrt(np.mean(e ** 2, axis=0))]}


def removed(open_loop: float, compensated: float, baseline: float = 0.0) -> float:
    """The fraction of the (open loop - baseline) error that compensation removed."""
    gap = open_loop - baseline
    return float((open_loop - compensated) / gap) if gap > 0 else float("nan")


TARGETS = {"ee_friction_error_removed": 0.80, "joint_torque_error_cut": 0.80}
THRUSTER_TARGET = 0.70  # thruster wrench RMS error (band-limited) cut, force and moment each
HEADROOM = 0.7          # the study's second case: the outer loop commands at most 70 % of each limit
THRUST_HEADROOM = 0.9   # and allocates at most 90 % of each thruster's maximum (the scenario's are 6 % weak)


def closed_loop_study(scenario, *, command_limit: float = 1.0, thrust_limit: float = 1.0,
                      settings: JointLoopSettings | None = None, progress: bool = False) -> tuple[dict, dict]:
    """The scenario three ways (no friction; friction, open loop; friction, compensated through the
    gateway in lockstep: joints and thrusters), the flight software's commands saturating at
    ``command_limit`` of the torque limits and its allocation at ``thrust_limit`` of each
    thruster's maximum in all three. Returns (figures for report.json, traces by case)."""
    import time

    import robot_description
    from simulator.engine import Simulation

    t0 = time.perf_counter()
    limit = robot_description.load(scenario.robot).effort_limit
    limits = {"command_limit": command_limit, "thrust_limit": thrust_limit}
    traces = {"no_friction": Simulation(scenario, friction=False, **limits).run(),
              "open_loop": Simulation(scenario, **limits).run()}
    traces["compensated"], info = run_compensated(scenario, settings=settings, progress=progress, **limits)
    ee = {case: ee_rms(tr) for case, tr in traces.items()}
    tq = {case: torque_rms(traces[case]) for case in ("open_loop", "compensated")}
    wr = {case: wrench_rms(traces[case]) for case in ("open_loop", "compensated")}
    raw = {case: wrench_rms(traces[case], None) for case in ("open_loop", "compensated")}
    thr = info["thrusters"]
    # the share of the valve timing alone: the same compensated run with the thruster loop on the
    # nominal wrenches (its fallback), so what the learned wrenches add is visible
    nominal, _ = run_compensated(scenario, settings=settings, thrusters_enabled=False, **limits)
    wr["nominal_wrenches"] = wrench_rms(nominal)
    out = {
        "command_limit_fraction": command_limit,
        "thrust_limit_fraction": thrust_limit,
        "ee_rms_error_m": ee,
        "joint_torque_rms_error_nm": tq,
        "thruster_wrench_rms_error": {**wr, "band_hz": BAND_HZ,
                                      "note": "actual - commanded (the flight software's allocated wrench), "
                                              f"band-limited to {BAND_HZ:g} Hz"},
        "thruster_wrench_rms_error_1khz": raw,
        "thruster_wrench_error_cut": {k: removed(wr["open_loop"][k], wr["compensated"][k])
                                      for k in ("force_n", "moment_nm")},
        "thruster_wrench_error_cut_nominal_wrenches": {k: removed(wr["open_loop"][k], wr["nominal_wrenches"][k])
                                                       for k in ("force_n", "moment_nm")},
        "thruster_target": THRUSTER_TARGET,
        "thruster_loop": {k: v for k, v in thr.items() if k not in ("closed", "applied")},
        "ee_friction_error_removed": {k: removed(ee["open_loop"][k], ee["compensated"][k], ee["no_friction"][k])
                                      for k in ee["open_loop"]},
        "joint_torque_error_cut": {k: removed(tq["open_loop"][k], tq["compensated"][k]) for k in tq["open_loop"]},
        "desired_at_torque_limit_fraction": {case: saturated_fraction(tr, limit * command_limit)
                                             for case, tr in traces.items()},
        "loop": {k: v for k, v in info.items() if k not in ("closed", "applied", "thrusters")},
        "settings": vars(settings or JointLoopSettings()),
        "thruster_settings": vars(ThrusterLoopSettings()),
        "targets": TARGETS,
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    out["pass"] = all(out[k]["overall"] >= v for k, v in TARGETS.items())
    out["thruster_pass"] = all(v >= THRUSTER_TARGET for v in out["thruster_wrench_error_cut"].values())
    return out, traces


def saturated_fraction(trace, limit_nm: np.ndarray) -> float:
    """The fraction of samples in which some joint's desired torque sat at the outer loop's limit
    ``limit_nm`` (n,) (at the drive's own limit, it leaves no room to compensate friction)."""
    limit = limit_nm
    return float(np.mean(np.any(np.abs(trace.arrays["tau_cmd"]) >= limit * (1 - 1e-9), axis=1)))


def missed(study: dict) -> list[str]:
    """The closed-loop targets missed, one phrase each."""
    out = [f"closed loop: {k.replace('_', ' ')} {100 * study[k]['overall']:.1f} % < {100 * v:.0f} %"
           for k, v in TARGETS.items() if not study[k]["overall"] >= v]
    cut = study.get("thruster_wrench_error_cut", {})
    out += [f"closed loop: thruster wrench error cut, {k.split('_')[0]} {100 * v:.1f} % < {100 * THRUSTER_TARGET:.0f} %"
            for k, v in cut.items() if not v >= THRUSTER_TARGET]
    return out


def format_table(study: dict, label: str) -> str:
    """The closed-loop figures ``bsc demo --closed-loop`` prints."""
    from harness.demo import columns

    ee, tq = study["ee_rms_error_m"], study["joint_torque_rms_error_nm"]
    keys = [k for k in ee["open_loop"] if k != "overall"] + ["overall"]
    rows = [("end-effector RMS error [m]", "no friction", "open loop", "compensated", "friction error removed")]
    for k in keys:
        rows.append((k, f"{ee['no_friction'][k]:.4f}", f"{ee['open_loop'][k]:.4f}", f"{ee['compensated'][k]:.4f}",
                     f"{100 * study['ee_friction_error_removed'][k]:.1f} %"))
    lines = [f"closed loop, {label}:"] + columns(rows, "lrrrr") + [""]
    rows = [("joint torque RMS error, actual - desired [N m]", "open loop", "compensated", "cut")]
    for k in tq["open_loop"]:
        rows.append((k, f"{tq['open_loop'][k]:.1f}", f"{tq['compensated'][k]:.1f}",
                     f"{100 * study['joint_torque_error_cut'][k]:.1f} %"))
    lines += columns(rows, "lrrr")
    w, raw = study["thruster_wrench_rms_error"], study["thruster_wrench_rms_error_1khz"]
    cut = study["thruster_wrench_error_cut"]
    lines += ["", f"thruster wrench RMS error, actual - commanded, {w['band_hz']:g} Hz band: force "
              f"{w['open_loop']['force_n']:.2f} -> {w['compensated']['force_n']:.2f} N "
              f"(cut {100 * cut['force_n']:.1f} %), moment {w['open_loop']['moment_nm']:.2f} -> "
              f"{w['compensated']['moment_nm']:.2f} N m (cut {100 * cut['moment_nm']:.1f} %); raw at 1 kHz "
              f"{raw['open_loop']['force_n']:.1f} -> {raw['compensated']['force_n']:.1f} N, "
              f"{raw['open_loop']['moment_nm']:.1f} -> {raw['compensated']['moment_nm']:.1f} N m",
              "desired torque at its limit (some joint): " + ", ".join(
                  f"{case} {100 * v:.0f} %" for case, v in study["desired_at_torque_limit_fraction"].items())]
    rt = study.get("realtime")
    if rt is not None:
        d, steps = rt["drives"] or {}, (rt["drives"] or {}).get("arm_steps_applied", {})
        delay = d.get("desired_frame_to_drive_command_us") or {}
        ee_rt = rt["ee_rms_error_m"]["compensated"]["overall"]
        lines += [f"real time across processes: end-effector RMS error {ee_rt:.4f} m, "
                  f"friction error removed {100 * rt['ee_friction_error_removed']['overall']:.1f} %, joint torque "
                  f"error cut {100 * rt['joint_torque_error_cut']['overall']:.1f} %",
                  f"  desired torques -> drive command at the robot: p50 {delay.get('p50_us', float('nan')):.0f} us, "
                  f"p99 {delay.get('p99_us', float('nan')):.0f} us; arm-steps under a closed-loop command "
                  f"{steps.get('closed', 0)}, open-loop {steps.get('open', 0)}, flight software's (none or later than "
                  f"{d.get('max_age_us', float('nan')) / 1e3:g} ms) {steps.get('late_or_none', 0)}"]
        wrt, cut_rt, v = rt.get("thruster_wrench_rms_error"), rt.get("thruster_wrench_error_cut"), rt.get("valves")
        if wrt and cut_rt and v:
            vd = v.get("first_step_to_arrival_us") or {}
            lines += [f"  thruster wrench error: force {wrt['compensated']['force_n']:.2f} N (cut "
                      f"{100 * cut_rt['force_n']:.1f} %), moment {wrt['compensated']['moment_nm']:.2f} N m (cut "
                      f"{100 * cut_rt['moment_nm']:.1f} %); valve schedules' first step -> arrival p50 "
                      f"{vd.get('p50_us', float('nan')):.0f} us, p99 {vd.get('p99_us', float('nan')):.0f} us; steps "
                      f"on the loop's valves {v['steps_external']} of {v['steps']} (rows late {v['rows_late']}, "
                      f"schedules too old {v['too_old']}), keep-out closed {v['keep_out_closed']} valve-steps"]
    return "\n".join(lines)


CASE_STYLE = {"no_friction": ("no friction", "tab:green", ":"),
              "open_loop": ("friction, open loop", "tab:red", "-"),
              "compensated": ("friction, compensated through the gateway", "tab:blue", "-"),
              "realtime": ("friction, compensated, real time across processes", "tab:purple", "--")}


def plot_ee_error(traces: dict, study: dict, path, title: str):
    """The paper's Figures 8-9 with the third curve: each end effector's position error over
    time, no friction / friction open loop / friction compensated (and compensated in real time
    when ``traces`` has it); dated."""
    import datetime

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = traces["open_loop"].meta["arms"]
    fig, axs = plt.subplots(len(arms), 1, figsize=(9, 2.6 * len(arms) + 1.0), sharex=True, squeeze=False)
    ee = {case: ee_rms(tr) for case, tr in traces.items()}
    for case, tr in traces.items():
        label, color, ls = CASE_STYLE[case]
        e = np.linalg.norm(tr["ee"] - tr["ee_des"], axis=2)
        # the no-friction curve on top, dotted: where compensation reaches it both stay visible
        top = case == "no_friction"
        for k, arm in enumerate(arms):
            axs[k, 0].plot(tr["t_s"], e[:, k], color=color, ls=ls, lw=2.2 if top else 1.4, zorder=4 if top else 2,
                           label=f"{label} (RMS {ee[case]['overall']:.3f} m)" if k == 0 else None)
    for k, arm in enumerate(arms):
        ax = axs[k, 0]
        rms = ", ".join(f"{c.replace('_', ' ')} {ee[c][arm]:.3f}" for c in traces)
        base, ol = ee["no_friction"][arm], ee["open_loop"][arm]
        gone = ", ".join(f"{c.replace('_', ' ')} {100 * removed(ol, ee[c][arm], base):.0f} %"
                         for c in traces if c in ("compensated", "realtime"))
        ax.set_title(f"{arm}: RMS {rms} m; friction error removed: {gone}", fontsize=8)
        ax.set_ylabel("error [m]")
        ax.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=8, loc="upper right")
    axs[-1, 0].set_xlabel("time [s]")
    today = datetime.date.today().isoformat()
    rt = study.get("realtime")
    realtime = ("" if rt is None else f"; real time: {100 * rt['ee_friction_error_removed']['overall']:.1f} %, "
                f"{100 * rt['joint_torque_error_cut']['overall']:.1f} %")
    fig.suptitle(f"End-effector position error |actual - desired|: {title}\n"
                 f"overall friction error removed {100 * study['ee_friction_error_removed']['overall']:.1f} %, "
                 f"joint torque error cut {100 * study['joint_torque_error_cut']['overall']:.1f} % (lockstep)"
                 f"{realtime}; {today}", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_joint_torques(traces: dict, study: dict, path, title: str):
    """Per joint: desired (the flight software's command) and actual torque, open loop and
    compensated; dated."""
    import datetime

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = traces["open_loop"].meta["joints"]
    cols = 2
    rows = (len(names) + 1) // cols
    fig, axs = plt.subplots(rows, cols, figsize=(13, 2.6 * rows + 1.2), sharex=True, squeeze=False)
    tq = study["joint_torque_rms_error_nm"]
    for j, name in enumerate(names):
        ax = axs[divmod(j, cols)]
        for case in ("open_loop", "compensated"):
            tr = traces[case]
            label, color, _ = CASE_STYLE[case]
            ax.plot(tr["t_s"], tr["tau_cmd"][:, j], color=color, ls="--", lw=1.0, label=f"desired, {label}")
            ax.plot(tr["t_s"], tr["tau_act"][:, j], color=color, lw=1.0, alpha=0.8, label=f"actual, {label}")
        ax.set_title(f"{name}: RMS actual - desired {tq['open_loop'][name]:.1f} -> {tq['compensated'][name]:.1f} N m",
                     fontsize=9)
        ax.set_ylabel("torque [N m]")
        ax.grid(alpha=0.3)
    for j in range(len(names), rows * cols):
        axs[divmod(j, cols)].axis("off")
    for c in range(cols):
        axs[-1, c].set_xlabel("time [s]")
    handles, labels = axs[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=4, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.97))
    fig.suptitle(f"Joint torques, desired vs actual: {title} (lockstep, {datetime.date.today().isoformat()})",
                 fontsize=10, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_thruster_wrench(traces: dict, study: dict, path, title: str):
    """Per axis: the commanded thruster wrench (the flight software's allocation) and the actual
    one band-limited to 20 Hz, open loop and compensated; dated."""
    import datetime

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from harness.demo import lowpass

    axes = ("fx [N]", "fy [N]", "fz [N]", "mx [N m]", "my [N m]", "mz [N m]")
    fig, axs = plt.subplots(3, 2, figsize=(13, 8.5), sharex=True, squeeze=False)
    w = study["thruster_wrench_rms_error"]
    for i, name in enumerate(axes):
        ax = axs[i % 3, i // 3]
        for case in ("open_loop", "compensated"):
            tr = traces[case]
            label, color, _ = CASE_STYLE[case]
            ax.plot(tr["t_s"], tr["thr_cmd"][:, i], color=color, ls="--", lw=0.9, label=f"commanded, {label}")
            ax.plot(tr["t_s"], lowpass(tr["thr_act"][:, i]), color=color, lw=1.0, alpha=0.8,
                    label=f"actual ({w['band_hz']:g} Hz), {label}")
        ax.set_title(f"{name.split()[0]}: RMS actual - commanded {w['open_loop']['per_axis'][i]:.2f} -> "
                     f"{w['compensated']['per_axis'][i]:.2f}", fontsize=9)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    for c in range(2):
        axs[-1, c].set_xlabel("time [s]")
    handles, labels = axs[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="upper center", ncol=4, fontsize=8, frameon=False, bbox_to_anchor=(0.5, 0.965))
    cut = study["thruster_wrench_error_cut"]
    fig.suptitle(f"Thruster wrench, commanded vs actual: {title}; error cut force {100 * cut['force_n']:.1f} %, "
                 f"moment {100 * cut['moment_nm']:.1f} % (lockstep, {datetime.date.today().isoformat()})",
                 fontsize=10, y=0.995)
    fig.tight_layout(rect=(0, 0, 1, 0.93))
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


# --- real time, across processes -------------------------------------------------------------

class _Inbox:
    """What the robot's drive and valve inboxes share: a subscription on ``key`` whose payloads are
    decoded by ``decode`` (a payload that is no command is counted in ``rejected``) and handed with
    their arrival time (host clock) to :meth:`_take`, under the lock, on zenoh's callback thread;
    the delays recorded there (``delays_ns``) as percentiles. A subclass sets its own state first:
    samples may arrive as soon as the subscription is declared."""

    def __init__(self, session, key: str, decode):
        import threading
        import time

        self.received = self.rejected = self.after_end = 0
        self.delays_ns: list[int] = []
        self._decode = decode
        self._lock = threading.Lock()
        self._ended = False
        self._last = time.monotonic()
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample) -> None:
        import time

        from gateway.control.messages import ControlError

        now = time.time_ns()
        try:
            cmd = self._decode(sample.payload.to_bytes())
        except ControlError:
            with self._lock:
                self.rejected += 1
            return
        with self._lock:
            self.received += 1
            self._last = time.monotonic()
            if self._ended:                  # after the robot's last step: counted, not applied
                self.after_end += 1
                return
            self._take(cmd, now)

    def _take(self, cmd, now_ns: int) -> None:
        raise NotImplementedError

    def end(self) -> None:
        """The robot's last step has gone out: what arrives from now on is counted in
        ``after_end`` (a loop that fell behind still answers every step it saw)."""
        import time

        with self._lock:
            self._ended = True
            self._last = time.monotonic()    # quiet is measured from here on

    def quiet_for(self) -> float:
        """Seconds since the last arrival (or since the subscription, before any)."""
        import time

        with self._lock:
            return time.monotonic() - self._last

    def close(self) -> None:
        self._sub.undeclare()

    def _delays(self) -> dict | None:
        x = sorted(self.delays_ns)
        if not x:
            return None
        pick = lambda q: round(x[min(len(x) - 1, int(q * len(x)))] / 1e3, 1)     # noqa: E731
        return {"p50_us": pick(0.5), "p90_us": pick(0.9), "p99_us": pick(0.99), "max_us": round(x[-1] / 1e3, 1),
                "n": len(x)}


class DriveInbox(_Inbox):
    """The simulated robot's drives on zenoh: the latest :class:`DriveCommand` of each arm from
    ``bsc/<robot>/commands/drives/**``, applied to ``sim`` (``external_drives=True``) at each
    step (:meth:`apply`, from :func:`simulator.firmware.run_on_buses`'s ``on_step``).

    A deadline, as a drive would enforce it: an arm's command is applied only while it is at most
    ``max_age_s`` older than the wall clock (its ``t_ns``, the stamp of the desired torques it
    corrects: host time in a real-time run); otherwise that arm's drives take the flight
    software's own latest command (open loop), so a late loop never applies stale torques.
    Latest-wins per arm (an older command arriving late is ignored). Records each command's
    delay from its desired torques to its arrival here, and per step and arm whether a fresh
    closed-loop command, a fresh open-loop one, or the flight software's command was applied."""

    def __init__(self, session, sim, *, max_age_s: float = 0.005):
        from gateway import keys
        from gateway.control.messages import decode_drive_command

        self.sim, self.max_age_ns = sim, int(max_age_s * 1e9)
        names = list(sim.robot.joint_names)
        self.cols = {a.name: [names.index(f"{a.name}/{j}") for j in a.joint_names] for a in sim.robot.arms}
        self.latest: dict[str, object] = {}
        self.steps = {"closed": 0, "open": 0, "late_or_none": 0}       # arm-steps by what the drives applied
        super().__init__(session, keys.drive_commands(sim.robot.name), decode_drive_command)

    def _take(self, cmd, now_ns: int) -> None:
        if cmd.arm not in self.cols or len(cmd.torque_nm) != len(self.cols[cmd.arm]):
            self.rejected += 1
            return
        old = self.latest.get(cmd.arm)
        if old is not None and old.t_ns >= cmd.t_ns:
            return
        self.latest[cmd.arm] = cmd
        self.delays_ns.append(now_ns - cmd.t_ns)

    def apply(self, readings=None, now_ns: int | None = None) -> None:
        """After a step went out: the drives' command for the next step (fresh commands from
        zenoh, the flight software's for the arms without one)."""
        import time

        now = time.time_ns() if now_ns is None else now_ns
        n = self.sim.robot.n_joints
        drive, use = np.zeros(n), np.zeros(n, dtype=bool)
        with self._lock:
            for arm, cols in self.cols.items():
                cmd = self.latest.get(arm)
                if cmd is None or now - cmd.t_ns > self.max_age_ns:
                    self.steps["late_or_none"] += 1
                    continue
                drive[cols] = cmd.torque_nm
                use[cols] = True
                self.steps["closed" if cmd.closed else "open"] += 1
        self.sim.command_drives(drive, use)

    def summary(self) -> dict:
        return {"received": self.received, "rejected": self.rejected, "max_age_us": self.max_age_ns / 1e3,
                "after_end": self.after_end, "arm_steps_applied": dict(self.steps),
                "desired_frame_to_drive_command_us": self._delays()}


class ValveInbox(_Inbox):
    """The simulated robot's valves on zenoh: the :class:`gateway.control.ThrusterValves` schedules of
    ``bsc/<robot>/commands/thrusters`` (``bsc control``'s thruster loop), given to ``sim``
    (``external_thrusters=True``) at each step (:meth:`apply`, from
    :func:`simulator.firmware.run_on_buses`'s ``on_step``, on the simulation's thread).

    Clocks: a schedule's times are those of the frames the gateway stamped (host time in a
    real-time run); host time ``t`` is step ``round((t - t0) / 1 ms)``, ``t0`` the host time step 0
    went out, estimated as the earliest ``now - step time`` seen after a step's frames were sent (a
    step never goes out before it is due). A deadline, as for the drives: a schedule that arrives
    more than ``max_age_s`` after its first step's time is not applied (those steps keep the flight
    software's valves); rows for steps already run are not applied either (the simulation counts
    them, ``valves_late``), nor are the steps no schedule covers. The controller allocates within
    the keep-out mask the commanded wrench carries (``THRUSTER_CMD_ALLOWED``); the robot's valve
    driver still closes any thruster its flight software excludes at the step (an interlock: the
    mask may change between a commanded wrench and a schedule's last rows), counted in
    ``keep_out_closed`` (valve-steps)."""

    def __init__(self, session, sim, *, max_age_s: float = 0.010):
        from gateway import keys
        from gateway.control.messages import decode_thruster_valves

        self.sim, self.max_age_ns = sim, int(max_age_s * 1e9)
        self.n = sim.layout.n
        self.bits = 1 << np.arange(self.n)
        self.t0_ns: int | None = None
        self.pending: list = []
        self.too_old = self.applied = self.keep_out_closed = self.before_start = 0
        super().__init__(session, keys.thruster_valves(sim.robot.name), decode_thruster_valves)

    def _take(self, v, now_ns: int) -> None:
        if v.valves >> self.n or any(m >> self.n for m in v.following) or len(v.duty) != self.n:
            self.rejected += 1
            return
        self.delays_ns.append(now_ns - v.t_ns)
        if now_ns - v.t_ns > self.max_age_ns:
            self.too_old += 1
            return
        self.pending.append(v)

    def apply(self, readings, now_ns: int | None = None) -> None:
        """After step ``readings`` went out: the schedules that arrived since, to the simulation."""
        import time

        from simulator.engine import DT_NS

        now = time.time_ns() if now_ns is None else now_ns
        t0 = now - readings.t_ns
        self.t0_ns = t0 if self.t0_ns is None else min(self.t0_ns, t0)
        with self._lock:
            todo, self.pending = self.pending, []
        for v in todo:
            k0 = round((v.t_ns - self.t0_ns) / DT_NS)
            if k0 < 0:
                self.before_start += 1
                continue
            rows = (np.array(v.masks(), dtype=np.int64)[:, None] & self.bits) != 0
            excluded = rows & ~self.sim.allowed
            self.keep_out_closed += int(excluded.sum())
            self.sim.command_valves(rows & self.sim.allowed, k0 * DT_NS)
            self.applied += 1

    def summary(self) -> dict:
        delays = self._delays()
        sim = self.sim
        with self._lock:
            pending = len(self.pending)
        return {"received": self.received, "rejected": self.rejected, "too_old": self.too_old,
                "applied": self.applied, "max_age_us": self.max_age_ns / 1e3,
                # arrived before the last step went out but not applied by then, after it (the
                # loop behind), or dated before step 0
                "pending_at_end": pending, "after_end": self.after_end, "before_start": self.before_start,
                "steps_external": int(sim.valves_external.sum()), "steps": int(sim.k),
                "rows_late": int(sim.valves_late), "keep_out_closed": self.keep_out_closed,
                "first_step_to_arrival_us": delays}


class RealtimeError(RuntimeError):
    """The real-time closed loop could not run (no network namespace, a process failed)."""


def run_realtime(scenario_name: str, workdir, *, duration_s: float | None = None, command_limit: float = 1.0,
                 thrust_limit: float = 1.0, thrusters: bool = False, rt_priority: int = 10, service_priority: int = 5,
                 say=print):
    """The closed loop in real time, across processes: ``bsc gateway`` (udp_multicast, the zenoh
    router), ``bsc control`` (joints and thrusters) and ``bsc sim --realtime --drives-from
    --valves-from`` (the robot, its drives and valves on zenoh), each its own process, CAN over
    udp_multicast in a private network namespace (root and iproute2, as the capacity benchmark);
    the robot at SCHED_FIFO ``rt_priority``, the gateway and the compensator at
    ``service_priority`` (0: normal scheduling). Returns (the compensated run's trace, the robot
    side's summary: frames, pacing, the drive commands' delays and the valve schedules').
    The joints; ``thrusters``: the thruster loop too (else the robot's valves keep the flight
    software's).
    ``BSC_DEBUG_CLOSED_LOOP=1`` in the environment prints the services' last output."""
    import os
    import signal
    import subprocess
    import sys
    from pathlib import Path

    import robot_description
    from drivers.wire import WireMap
    from gateway.zenoh_config import free_port
    from simulator import scenario as scenarios
    from simulator.truth import Trace

    root = Path(__file__).resolve().parents[1]
    try:
        from benchmarks.bench_latency import private_netns
    except ImportError:
        # the benchmarks live in the source tree beside the packages (as bsc bench finds them)
        if not (root / "benchmarks" / "bench_latency.py").is_file():
            raise RealtimeError(f"the real-time closed loop needs the source tree: no benchmarks/ in {root}") from None
        sys.path.insert(0, str(root))
        sys.modules.pop("benchmarks", None)
        from benchmarks.bench_latency import private_netns
    workdir = Path(workdir)
    sc = scenarios.load(scenario_name, {} if duration_s is None else {"duration_s": duration_s})
    robot = robot_description.load(sc.robot)
    buses = list(WireMap.from_robot(robot).buses)
    channels = [a for i, b in enumerate(buses) for a in ("-c", f"{b}=239.74.163.{i + 1}")]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1")
    with private_netns() as ns:
        if ns is None:
            raise RealtimeError("needs root and iproute2: CAN goes over udp_multicast in a private network namespace")
        inside = ["ip", "netns", "exec", ns, sys.executable, "-m", "gateway.cli"]
        # the gateway and the compensator at real-time priority too (below the robot's), as on a
        # robot's computer: other load on the host must not hold the loop back
        served = ["ip", "netns", "exec", ns, *(["chrt", "-f", str(service_priority)] if service_priority else []),
                  sys.executable, "-m", "gateway.cli"]
        ep = f"tcp/127.0.0.1:{free_port()}"
        run_for = str(sc.duration_s + 300)
        procs = []

        def start(args, what, ready, stream):
            p = subprocess.Popen(served + args, cwd=root, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                                 stderr=subprocess.PIPE, text=True)
            procs.append(p)
            line = getattr(p, stream).readline()
            if ready not in line:
                err = p.stderr.read()[-2000:] if stream == "stdout" else ""
                raise RealtimeError(f"{what} did not start: {line} {err}")
            return p

        try:
            start(["gateway", "-i", "udp_multicast", *channels, "--mode", "router", "--listen", ep, "--robot", sc.robot,
                   "--duration", run_for], "bsc gateway", "receive", "stdout")
            start(["control", "--mode", "client", "--connect", ep, "--robot", sc.robot, "--duration", run_for,
                   *(["--thruster-loop"] if thrusters else [])],
                  "bsc control", "bsc control:", "stderr")
            say(f"closed loop in real time: {sc.name}, {sc.duration_s:g} s, gateway + control + robot processes")
            out = workdir / "sim"
            sim = subprocess.run(inside + ["sim", "--scenario", scenario_name, "--duration", f"{sc.duration_s:g}",
                                           "--interface", "udp_multicast", *channels, "--realtime",
                                           "--rt-priority", str(rt_priority), "--drives-from", ep,
                                           *(["--valves-from", ep] if thrusters else []),
                                           "--command-limit", f"{command_limit:g}",
                                           "--thrust-limit", f"{thrust_limit:g}", "--no-plots", "--no-compare",
                                           "--quiet", "--out", str(out)],
                                 cwd=root, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True,
                                 timeout=3 * sc.duration_s + 300)
            if sim.returncode != 0:
                raise RealtimeError(f"the robot's process failed: {sim.stderr[-2000:]}")
        finally:
            ends = []
            for p in procs:
                if p.poll() is None:
                    p.send_signal(signal.SIGINT)
                try:
                    ends.append(p.communicate(timeout=60))
                except subprocess.TimeoutExpired:
                    p.kill()
                    ends.append(p.communicate())
            if os.environ.get("BSC_DEBUG_CLOSED_LOOP"):            # the services' last words, to diagnose a run
                for p, (o, e) in zip(procs, ends):
                    name = p.args[p.args.index("gateway.cli") + 1]
                    say(f"--- bsc {name}, exit status {p.returncode}\n{o[-1500:]}\n{e[-1500:]}")
    import json

    summary = json.loads((out / "summary.json").read_text())["can"]
    # what bsc control sent, from its last line: every command should reach the robot (in time or not)
    import re

    said = ends[1][1] if len(ends) > 1 else ""
    m = re.search(r"drive commands out: (\d+) closed loop, (\d+) open loop"
                  r"(?:; valve commands out: (\d+) on learned wrenches, (\d+) on nominal ones)?", said)
    if m:
        summary["control_sent"] = {"drives": int(m[1]) + int(m[2]),
                                   "valves": int(m[3]) + int(m[4]) if m[3] is not None else 0}
    return Trace.load(out / "truth.npz"), summary


def realtime_study(scenario_arg: str, scenario, study: dict, traces: dict, workdir, *, command_limit: float = 1.0,
                   thrusters: bool = False, say=print) -> dict:
    """The real-time compensated run of ``scenario`` (``scenario_arg``: its name or file, as
    ``bsc sim --scenario`` takes it) beside a lockstep study's no-friction and open-loop runs (the
    same deterministic simulations, with the study's command and thrust limits): the same figures,
    the loops' delays and the pacing. The joints; ``thrusters``: the thruster loop too. Adds the
    run's trace to ``traces`` as ``realtime``."""
    thrust_limit = study.get("thrust_limit_fraction", 1.0)
    trace, summary = run_realtime(scenario_arg, workdir, duration_s=scenario.duration_s,
                                  command_limit=command_limit, thrust_limit=thrust_limit, thrusters=thrusters, say=say)
    ee = {"no_friction": study["ee_rms_error_m"]["no_friction"], "open_loop": study["ee_rms_error_m"]["open_loop"],
          "compensated": ee_rms(trace)}
    tq = {"open_loop": study["joint_torque_rms_error_nm"]["open_loop"], "compensated": torque_rms(trace)}
    wr = {"open_loop": study["thruster_wrench_rms_error"]["open_loop"], "compensated": wrench_rms(trace)}
    out = {"command_limit_fraction": command_limit, "thrust_limit_fraction": thrust_limit, "thrusters": thrusters,
           "ee_rms_error_m": ee, "joint_torque_rms_error_nm": tq,
           "thruster_wrench_rms_error": {**wr, "band_hz": BAND_HZ,
                                         **({} if thrusters else {"note": "thrusters not compensated: the joint "
                                                                          "loop only"})},
           "thruster_wrench_error_cut": {k: removed(wr["open_loop"][k], wr["compensated"][k])
                                         for k in ("force_n", "moment_nm")},
           "ee_friction_error_removed": {k: removed(ee["open_loop"][k], ee["compensated"][k], ee["no_friction"][k])
                                         for k in ee["open_loop"]},
           "joint_torque_error_cut": {k: removed(tq["open_loop"][k], tq["compensated"][k]) for k in tq["open_loop"]},
           "drives": summary.get("drives"), "valves": summary.get("valves"), "pacing": summary.get("pacing"),
           "frames_sent": summary.get("frames_sent")}
    out["pass"] = all(out[k]["overall"] >= v for k, v in TARGETS.items())
    traces["realtime"] = trace
    return out
