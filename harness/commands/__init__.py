"""The harness's ``bsc`` subcommands (``bsc demo``, ``bsc sim``), loaded by name by ``gateway.cli``."""
