"""One module per ``bsc`` subcommand, each with ``add_arguments(parser)`` and ``run(args) -> int``.

They are imported lazily by :mod:`gateway.cli`, so ``bsc --help`` does not pay for Pinocchio,
zenoh or matplotlib.
"""
