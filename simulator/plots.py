"""PNG figures of a truth trace, after the paper's: trajectories, end-effector error, commanded
vs actual joint torques and thruster wrench, with the gateway's estimates when given.
matplotlib with the Agg backend (no display)."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable

import numpy as np

from .truth import Trace

AXES = ["fx [N]", "fy [N]", "fz [N]", "mx [N m]", "my [N m]", "mz [N m]"]
# Estimates are drawn in these colours, in the order given; truth is black, commands blue, so
# that no estimate can share a colour with what it is compared to.
ESTIMATE_COLORS = ("tab:red", "tab:green", "tab:purple", "tab:brown")
COMMANDED = "tab:blue"
ACTUAL = "black"


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def spacecraft_radius(urdf: str) -> tuple[float, str]:
    """Radius of the spacecraft's outline in its x-y plane, m, and where it came from.

    A cylinder in the root link's ``<visual>`` or ``<collision>`` if the URDF has one; otherwise
    the farthest arm mount (F/T sensor origin) from C, since the arms sit on the rim."""
    import robot_description

    root = ET.fromstring(urdf)
    children = {j.find("child").get("link") for j in root.iter("joint") if j.find("child") is not None}
    base = next((link for link in root.iter("link") if link.get("name") not in children), None)
    if base is not None:
        for cyl in base.findall("./visual/geometry/cylinder") + base.findall("./collision/geometry/cylinder"):
            try:
                return float(cyl.get("radius")), "URDF cylinder"
            except (TypeError, ValueError):
                continue
    robot = robot_description.from_urdf_text(urdf)
    return max(float(np.hypot(*arm.r_sc[:2])) for arm in robot.arms), "arm mounts"


def _rotation_xyzw(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def trajectories(tr: Trace, path: Path) -> Path:
    """End effectors (actual, desired), the spacecraft's centre C and outline, the target's rim;
    inertial x-y plane, m."""
    import robot_description

    plt = _plt()
    base = tr["q"][:, :2]
    radius, source = spacecraft_radius(tr.meta["urdf"])
    robot = robot_description.from_urdf_text(tr.meta["urdf"])
    p0, R0 = tr["q"][0, :3], _rotation_xyzw(tr["q"][0, 3:7])
    mounts = np.array([p0 + R0 @ arm.r_sc for arm in robot.arms])
    th = np.linspace(0, 2 * np.pi, 200)
    rim = base[0] + radius * np.c_[np.cos(th), np.sin(th)]
    pts = [rim, base, tr["ee"][:, :, :2].reshape(-1, 2), tr["ee_des"][:, :, :2].reshape(-1, 2)]
    sc, r_target = tr.meta.get("target_center_m"), tr.meta.get("target_radius_m")
    if sc:
        target = np.asarray(sc[:2]) + r_target * np.c_[np.cos(th), np.sin(th)]
        pts.append(target)
    lo, hi = np.min([p.min(axis=0) for p in pts], axis=0), np.max([p.max(axis=0) for p in pts], axis=0)
    pad = 0.05 * max(hi - lo)
    lo, hi = lo - pad, hi + pad
    # equal scales on both axes: the figure takes the data's aspect ratio, the legend goes below
    w = 8.0
    fig, ax = plt.subplots(figsize=(w, max(3.0, w * (hi[1] - lo[1]) / (hi[0] - lo[0]))))
    ax.plot(rim[:, 0], rim[:, 1], color="0.55", lw=1.0,
            label=f"spacecraft outline at t = 0 (r = {radius:.2f} m, from the {source})")
    ax.plot(mounts[:, 0], mounts[:, 1], "s", color="0.35", ms=5, label="arm mounts (F/T sensors) at t = 0")
    ax.plot(base[:, 0], base[:, 1], "k-", lw=2, label="spacecraft centre of mass C")
    for k, arm in enumerate(tr.meta["arms"]):
        line, = ax.plot(tr["ee"][:, k, 0], tr["ee"][:, k, 1], lw=1.5, label=f"{arm} end effector")
        ax.plot(tr["ee_des"][:, k, 0], tr["ee_des"][:, k, 1], "--", lw=1, color=line.get_color(), alpha=0.7,
                label=f"{arm} desired")
        ax.plot(*tr["ee"][0, k, :2], "o", color=line.get_color(), ms=4)
    if sc:
        ax.plot(target[:, 0], target[:, 1], ":", color="gray", label=f"target rim (r = {r_target:g} m)")
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.set_xlabel("x [m] (inertial)")
    ax.set_ylabel("y [m] (inertial)")
    ax.set_title(f"Trajectories in the inertial x-y plane ({tr.meta['scenario']}, "
                 f"{tr['t_s'][-1] + tr.meta['dt_s']:g} s; dots: start)", fontsize=10)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.1), ncol=2, frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


def ee_error(traces: dict[str, Trace], path: Path) -> Path:
    plt = _plt()
    first = next(iter(traces.values()))
    arms = first.meta["arms"]
    fig, axs = plt.subplots(len(arms), 1, figsize=(8, 2.4 * len(arms)), sharex=True, squeeze=False)
    for label, tr in traces.items():
        e = np.linalg.norm(tr["ee"] - tr["ee_des"], axis=2)
        for k, arm in enumerate(arms):
            axs[k, 0].plot(tr["t_s"], e[:, k], label=label)
    for k, arm in enumerate(arms):
        axs[k, 0].set_ylabel(f"{arm} error [m]")
        axs[k, 0].grid(alpha=0.3)
    axs[0, 0].legend(fontsize=8)
    axs[-1, 0].set_xlabel("time [s]")
    fig.suptitle("End-effector position error |actual - desired|")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _legend_on_top(fig, axs, title: str) -> None:
    """One legend for the whole figure, between the title and the plots, so it hides no data.
    Called after the layout is done (tight_layout would make room for them twice)."""
    h = fig.get_figheight()
    titled = any(ax.get_title() for ax in axs.flat)       # panel titles need room of their own
    fig.subplots_adjust(top=1 - (0.95 if titled else 0.75) / h)
    handles, labels = axs.flat[0].get_legend_handles_labels()
    fig.suptitle(title, fontsize=11, y=1 - 0.1 / h, va="top")
    leg = fig.legend(handles, labels, loc="upper center", ncol=min(len(labels), 4), fontsize=8,
                     bbox_to_anchor=(0.5, 1 - 0.35 / h), frameon=False)
    for line in leg.get_lines():          # thin or faint lines would not show in the key
        line.set_linewidth(max(line.get_linewidth(), 2.0))
        line.set_alpha(max(line.get_alpha() or 1.0, 0.6))


def joint_torques(tr: Trace, path: Path, estimates: dict[str, np.ndarray] | None = None,
                  notes: dict[str, str] | None = None) -> Path:
    """Commanded and actual torque of every joint, N m; optional estimates (N, n) by label,
    drawn in the order given, later ones on top; ``notes`` (by joint name) go in the panel titles."""
    plt = _plt()
    names = tr.meta["joints"]
    arms = tr.meta["arms"]
    by_arm = [[j for j, name in enumerate(names) if name.split("/", 1)[0] == arm] for arm in arms]
    if 1 < len(arms) <= 4:            # one column per arm, proximal joint on top
        cols, rows = len(arms), max(map(len, by_arm))
        cells = {j: (r, c) for c, js in enumerate(by_arm) for r, j in enumerate(js)}
    else:
        cols = 2 if len(names) > 1 else 1
        rows = (len(names) + cols - 1) // cols
        cells = {j: divmod(j, cols) for j in range(len(names))}
    fig, axs = plt.subplots(rows, cols, figsize=((6.5 if cols < 3 else 5.5) * cols, 2.5 * rows + 1.2),
                            sharex=True, squeeze=False)
    t = tr["t_s"]
    for j, name in enumerate(names):
        ax = axs[cells[j]]
        # actual: a wide grey band under everything, so an estimate on top of it still shows it
        ax.plot(t, tr["tau_act"][:, j], lw=4, color="0.7", solid_capstyle="butt", zorder=1,
                label="actual (motor minus friction)")
        ax.plot(t, tr["tau_cmd"][:, j], lw=1.2, ls="-.", color=COMMANDED, zorder=2, label="commanded")
        for i, (label, est) in enumerate((estimates or {}).items()):
            # later estimates dashed on top: where two coincide (the first joint) both still show
            ax.plot(t[: len(est)], est[:, j], lw=0.9, color=ESTIMATE_COLORS[i % len(ESTIMATE_COLORS)],
                    ls="-" if i == 0 else (0, (4, 2)), zorder=3 + i, label=label)
        ax.set_title(name + (f"   {notes[name]}" if notes and name in notes else ""), fontsize=9)
        ax.set_ylabel("torque [N m]")
        ax.grid(alpha=0.3)
    used = set(cells.values())
    for c in range(cols):
        bottom = max((r for r, cc in used if cc == c), default=None)
        for r in range(rows):
            if (r, c) not in used:
                axs[r, c].axis("off")
        if bottom is not None:        # a shorter column still gets its time axis
            axs[bottom, c].xaxis.set_tick_params(labelbottom=True)
            axs[bottom, c].set_xlabel("time [s]")
    title = ("Joint torques: commanded, actual and estimated from the base F/T sensors" if estimates
             else "Joint torques: commanded vs actual (motor minus friction)")
    fig.tight_layout()
    _legend_on_top(fig, axs, title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def thruster_wrench(tr: Trace, path: Path, estimates: dict[str, np.ndarray] | None = None,
                    band: tuple[str, Callable[[np.ndarray], np.ndarray]] | None = None,
                    notes: list[str] | None = None) -> Path:
    """Commanded, actual and estimated thruster force and moment (body frame, about C), 6 axes.

    The actual wrench is 1 kHz valve pulses. With ``band = (label, filter)``, ``filter`` maps an
    (N, 6) array to its band-limited version (the one the accuracy figures use): the actual and
    every estimate are drawn band-limited over the faint raw pulses, and the axes are scaled to
    the band-limited curves. ``notes`` (one per axis) go in the panel titles."""
    plt = _plt()
    fig, axs = plt.subplots(3, 2, figsize=(12, 8), sharex=True)
    t = tr["t_s"]
    act, cmd = tr["thr_act"], tr["thr_cmd"]
    label, lowpass = band if band is not None else ("", None)
    act_b = lowpass(act) if lowpass else None
    est_b = {k: (lowpass(v) if lowpass else v) for k, v in (estimates or {}).items()}
    for i in range(6):
        ax = axs[i % 3, i // 3]
        ax.plot(t, act[:, i], lw=0.5, color="tab:orange", alpha=0.25 if lowpass else 0.6, zorder=1,
                label="actual, raw 1 kHz valve pulses")
        ax.plot(t, cmd[:, i], lw=1.2, color=COMMANDED, zorder=3, label="commanded (allocated)")
        shown = [cmd[:, i]]
        if act_b is not None:
            ax.plot(t, act_b[:, i], lw=2.2, color=ACTUAL, zorder=2, label=f"actual, {label}")
            shown.append(act_b[:, i])
        for k, (name, est) in enumerate(est_b.items()):
            ax.plot(t[: len(est)], est[:, i], lw=1.0, color=ESTIMATE_COLORS[k % len(ESTIMATE_COLORS)], zorder=4 + k,
                    label=f"{name}, {label}" if lowpass else name)
            shown.append(est[:, i])
        if lowpass:
            # scaled to what is judged; the raw pulses run off the axes
            lo, hi = min(np.nanmin(s) for s in shown), max(np.nanmax(s) for s in shown)
            pad = 0.15 * max(hi - lo, 1e-3)
            ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel(AXES[i])
        if notes:
            ax.set_title(notes[i], fontsize=9)
        ax.grid(alpha=0.3)
    axs[-1, 0].set_xlabel("time [s]")
    axs[-1, 1].set_xlabel("time [s]")
    title = "Thruster force and moment (body frame, about C): commanded vs actual"
    if estimates:
        title = (f"Thruster force and moment (body frame, about C): {' and '.join(estimates)}"
                 f" vs actual" + (f", {label}" if lowpass else ""))
    fig.tight_layout()
    _legend_on_top(fig, axs, title)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
