"""The closed inner loop, in lockstep: the simulated robot's joint drives take their commands from
the compensator (:class:`gateway.control.JointCompensator`) fed by the gateway's session engine on
the firmware's own frames.

Per 1 ms step: the simulator steps (its flight software computes the desired torques, the drives
apply the latest command they were given), the sensor firmware encodes the step's frames, the
session decodes them and estimates the efforts; the compensator sees the desired torques the arm
bus carried (``TorqueCommand`` samples, every 2 ms) and the estimates, and each completed set of
desired torques becomes the drives' command for the following steps. The correction is therefore
one step late, as it would be through the wire, and the run is deterministic.

:func:`closed_loop_study` runs the scenario three ways (no friction; friction, open loop; friction,
compensated) and returns the figures of ``report.json``'s ``closed_loop`` block.
"""
from __future__ import annotations

import numpy as np

from drivers.samples import TorqueCommand
from gateway.control import JointCompensator, JointLoopSettings
from gateway.efforts import JointEfforts


def run_compensated(scenario, *, settings: JointLoopSettings | None = None, enabled: bool = True,
                    command_limit: float = 1.0, faults=None, progress: bool = False):
    """Simulator -> firmware frames -> session -> compensator -> the simulator's drives, in
    lockstep in this thread. ``faults``: the firmware's fault injection
    (:class:`simulator.firmware.Faults`). Returns (trace, info): ``info`` counts the commands
    issued closed and open per arm and the flags they carried, lists the loop's transitions, and
    ``closed`` (N, p) says per step whether each arm's drives were under a closed-loop command,
    ``applied`` (N, n) is the command the drives applied, N m."""
    from gateway.engine import Session, Sink
    from robot_description.thrusters import ThrusterLayout
    from simulator.engine import Simulation
    from simulator.firmware import Firmware
    from simulator.progress import SimProgress

    sim = Simulation(scenario, external_drives=True, command_limit=command_limit)
    robot = sim.robot
    fw = Firmware(robot, faults=faults)
    comp = JointCompensator.for_robot(robot, settings, enabled=enabled)
    names = list(robot.joint_names)
    cols = {a.name: [names.index(f"{a.name}/{j}") for j in a.joint_names] for a in robot.arms}
    ready: list[str] = []

    class Feed(Sink):
        def emit(self, key, obj, log_ns) -> None:
            if isinstance(obj, JointEfforts):
                comp.estimate(obj)
            elif isinstance(obj, TorqueCommand):
                arm = comp.observe(obj)
                if arm is not None:
                    ready.append(arm)

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
            bar.update(sim.k)
    ses.close()
    events = [{"arm": e.arm, "t_s": e.t_ns * 1e-9, "state": e.state, "reason": e.reason} for e in comp.events]
    return sim.trace, {"commands": counts, "flags": flags, "transitions": events, "closed": closed,
                       "applied": sim.drive_applied}


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


def wrench_rms(trace) -> dict:
    """RMS of the actual thruster wrench minus the one the allocation demanded, force N and
    moment N m (vector norms over the three axes)."""
    A = trace.arrays
    e = A["thr_act"] - A["thr_cmd"]
    return {"force_n": float(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1)))),
            "moment_nm": float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1))))}


def removed(open_loop: float, compensated: float, baseline: float = 0.0) -> float:
    """The fraction of the (open loop - baseline) error that compensation removed."""
    gap = open_loop - baseline
    return float((open_loop - compensated) / gap) if gap > 0 else float("nan")


TARGETS = {"ee_friction_error_removed": 0.80, "joint_torque_error_cut": 0.80}
HEADROOM = 0.7          # the study's second case: the outer loop commands at most 70 % of each limit


def closed_loop_study(scenario, *, command_limit: float = 1.0, settings: JointLoopSettings | None = None,
                      progress: bool = False) -> tuple[dict, dict]:
    """The scenario three ways (no friction; friction, open loop; friction, compensated through the
    gateway in lockstep), the flight software's commands saturating at ``command_limit`` of the
    torque limits in all three. Returns (figures for report.json, traces by case)."""
    import time

    import robot_description
    from simulator.engine import Simulation

    t0 = time.perf_counter()
    limit = robot_description.load(scenario.robot).effort_limit
    traces = {"no_friction": Simulation(scenario, friction=False, command_limit=command_limit).run(),
              "open_loop": Simulation(scenario, command_limit=command_limit).run()}
    traces["compensated"], info = run_compensated(scenario, settings=settings, command_limit=command_limit,
                                                  progress=progress)
    ee = {case: ee_rms(tr) for case, tr in traces.items()}
    tq = {case: torque_rms(traces[case]) for case in ("open_loop", "compensated")}
    wr = {case: wrench_rms(traces[case]) for case in ("open_loop", "compensated")}
    out = {
        "command_limit_fraction": command_limit,
        "ee_rms_error_m": ee,
        "joint_torque_rms_error_nm": tq,
        "thruster_wrench_rms_error": {**wr, "note": "thrusters not compensated: the joint loop only"},
        "ee_friction_error_removed": {k: removed(ee["open_loop"][k], ee["compensated"][k], ee["no_friction"][k])
                                      for k in ee["open_loop"]},
        "joint_torque_error_cut": {k: removed(tq["open_loop"][k], tq["compensated"][k]) for k in tq["open_loop"]},
        "desired_at_torque_limit_fraction": {case: saturated_fraction(tr, limit * command_limit)
                                             for case, tr in traces.items()},
        "loop": {k: v for k, v in info.items() if k not in ("closed", "applied")},
        "settings": vars(settings or JointLoopSettings()),
        "targets": TARGETS,
        "wall_s": round(time.perf_counter() - t0, 2),
    }
    out["pass"] = all(out[k]["overall"] >= v for k, v in TARGETS.items())
    return out, traces


def saturated_fraction(trace, limit_nm: np.ndarray) -> float:
    """The fraction of samples in which some joint's desired torque sat at the outer loop's limit
    ``limit_nm`` (n,) (at the drive's own limit, it leaves no room to compensate friction)."""
    limit = limit_nm
    return float(np.mean(np.any(np.abs(trace.arrays["tau_cmd"]) >= limit * (1 - 1e-9), axis=1)))


def missed(study: dict) -> list[str]:
    """The closed-loop targets missed, one phrase each."""
    return [f"closed loop: {k.replace('_', ' ')} {100 * study[k]['overall']:.1f} % < {100 * v:.0f} %"
            for k, v in TARGETS.items() if not study[k]["overall"] >= v]


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
    w = study["thruster_wrench_rms_error"]
    lines += ["", f"thruster wrench RMS error (not compensated): force {w['open_loop']['force_n']:.1f} -> "
              f"{w['compensated']['force_n']:.1f} N, moment {w['open_loop']['moment_nm']:.1f} -> "
              f"{w['compensated']['moment_nm']:.1f} N m",
              "desired torque at its limit (some joint): " + ", ".join(
                  f"{case} {100 * v:.0f} %" for case, v in study["desired_at_torque_limit_fraction"].items())]
    return "\n".join(lines)


CASE_STYLE = {"no_friction": ("no friction", "tab:green", ":"),
              "open_loop": ("friction, open loop", "tab:red", "-"),
              "compensated": ("friction, compensated through the gateway", "tab:blue", "-")}


def plot_ee_error(traces: dict, study: dict, path, title: str):
    """The paper's Figures 8-9 with the third curve: each end effector's position error over
    time, no friction / friction open loop / friction compensated; dated."""
    import datetime

    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    arms = traces["open_loop"].meta["arms"]
    fig, axs = plt.subplots(len(arms), 1, figsize=(9, 2.6 * len(arms) + 1.0), sharex=True, squeeze=False)
    ee = study["ee_rms_error_m"]
    for case, tr in traces.items():
        label, color, ls = CASE_STYLE[case]
        e = np.linalg.norm(tr["ee"] - tr["ee_des"], axis=2)
        for k, arm in enumerate(arms):
            axs[k, 0].plot(tr["t_s"], e[:, k], color=color, ls=ls, lw=1.4,
                           label=f"{label} (RMS {ee[case][arm]:.3f} m)" if k == 0 else None)
    for k, arm in enumerate(arms):
        ax = axs[k, 0]
        rms = ", ".join(f"{c.replace('_', ' ')} {ee[c][arm]:.3f}" for c in traces)
        removed_pct = 100 * study["ee_friction_error_removed"][arm]
        ax.set_title(f"{arm}: RMS {rms} m; friction error removed {removed_pct:.0f} %", fontsize=9)
        ax.set_ylabel("error [m]")
        ax.grid(alpha=0.3)
    axs[0, 0].legend(fontsize=8, loc="upper right")
    axs[-1, 0].set_xlabel("time [s]")
    today = datetime.date.today().isoformat()
    fig.suptitle(f"End-effector position error |actual - desired|: {title}\n"
                 f"overall friction error removed {100 * study['ee_friction_error_removed']['overall']:.1f} %, "
                 f"joint torque error cut {100 * study['joint_torque_error_cut']['overall']:.1f} % (lockstep, {today})",
                 fontsize=10)
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
