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
