"""One module per ``bsc`` subcommand, each with ``add_arguments(parser)`` and ``run(args) -> int``.

They are imported lazily by :mod:`gateway.cli`, so ``bsc --help`` does not pay for Pinocchio,
zenoh or matplotlib.
"""


def stop_on_sigterm():
    """``(stop, restore)``: a ``threading.Event`` that SIGTERM sets (the handler is installed only
    on the main thread, where Python allows it), and the function that puts the previous handler
    back. Long-running commands (gateway, monitor, record, replay) stop cleanly on it."""
    import signal
    import threading

    stop = threading.Event()
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, lambda *_: stop.set())

    def restore() -> None:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)

    return stop, restore


RT_PRIORITY_HELP = ("run at SCHED_FIFO priority N (1-99; root or CAP_SYS_NICE), as sensor hardware would, so "
                    "that other load on the host does not delay the frames (the run reports how late they "
                    "went out; docs/firmware.md)")


def check_interface(args) -> None:
    """The bus flags mean nothing without a bus: one line, exit status 2."""
    from gateway.cli import UserError

    if not getattr(args, "interface", None) and (getattr(args, "bitrate", None) is not None
                                                 or getattr(args, "data_bitrate", None) is not None
                                                 or getattr(args, "bus_kwarg", None)):
        raise UserError("--bitrate, --data-bitrate and --bus-kwarg are for the CAN buses: give --interface")


def check_rt_priority(n: int) -> None:
    """A ``--rt-priority`` value: 0 (off) or 1-99, else a one-line UserError."""
    if n and not 1 <= n <= 99:
        from gateway.cli import UserError

        raise UserError(f"--rt-priority must be 1-99, got {n}")


def set_rt_priority(n: int) -> None:
    """Run this process at SCHED_FIFO priority ``n`` (nothing for 0); a one-line UserError when
    the system does not allow it. For the commands that stand in for hardware on the buses
    (``bsc sim --realtime``, ``bsc replay -i``): a receiver stamping frames on arrival sees any
    scheduling delay of theirs as sensor timing."""
    import os

    from gateway.cli import UserError

    if not n:
        return
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(n))
    except PermissionError:
        raise UserError(f"--rt-priority {n}: SCHED_FIFO needs root or CAP_SYS_NICE "
                        "(or run without it and read the lateness it reports)") from None
