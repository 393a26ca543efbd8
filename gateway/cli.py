"""The ``bsc`` command line: one entry point, one subcommand per job.

Errors are one clear line on stderr and a non-zero exit; ``--debug`` shows the traceback.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

from gateway.errors import GatewayError

# name -> (module in gateway.commands, or a full module path, one-line help). Imported only when
# chosen: the harness's commands (demo, sim: they run the simulator) are found by name, so the
# product never imports the harness or the simulator, and an install without them says so.
COMMANDS: dict[str, tuple[str, str]] = {
    "demo": ("harness.commands.demo", "the main job: the paper's capture scenario end to end, with report and figures"),
    "gateway": ("gateway", "drivers and estimator of a robot: samples, efforts and health over zenoh"),
    "budget": ("budget", "print the worst-case CAN bus load per bus of a robot at nominal rates"),
    "sim": ("harness.commands.sim", "run the simulated space robot (lockstep) and write its truth trace and plots"),
    "info": ("info", "summarise an MCAP log: channels, rates, gaps, metadata, complete or truncated"),
    "recover": ("recover", "salvage a truncated MCAP log (crash, kill, full disk) into a valid file"),
    "record": ("record", "record a session to MCAP: raw CAN frames per bus and every zenoh sample"),
    "import": ("import_log", "convert a CAN log (candump .log, .asc, .blf, .trc, .csv) into a session MCAP"),
    "export": ("export", "write a session's raw CAN frames as a candump .log, .asc, .blf, .trc or .csv file"),
    "replay": ("replay", "replay a log offline through drivers + estimator, or live onto CAN or zenoh"),
    "monitor": ("monitor", "live monitoring over zenoh: residuals, friction, efficiency, sensor health, alerts"),
    "control": ("control", "close the inner loop: joint drive commands corrected from the estimated torques"),
    "analyze": ("analyze", "actuator and sensor degradation from recorded sessions: friction, efficiency, trends"),
    "bench": ("bench", "run every benchmark: figures beside anchors of the same run, as ratios"),
}


# Exit statuses: CI and scripts tell these apart.
EXIT_OK = 0
EXIT_FAILURE = 1            # a bug or an unexpected failure (one line; --debug for the traceback)
EXIT_USAGE = 2              # an error the user can fix: bad option, bad file
EXIT_TARGETS_MISSED = 3     # the run completed, and its judged results missed their targets
#                             (bsc demo; bsc replay --check)
EXIT_INTERRUPTED = 130      # Ctrl-C, as a shell reports SIGINT


class UserError(GatewayError):
    """An error the user can fix (bad file, bad option): printed as one line, exit status 2."""


PROJECT_PACKAGES = ("gateway", "drivers", "simulator", "robot_description", "harness")


def is_project_error(exc: BaseException) -> bool:
    """An error the project raised on purpose: of a class defined in one of its packages (each
    package's errors derive from its own root: DriverError, GatewayError, SimulatorError,
    DescriptionError). The CLI tells the user about these in one line; any other exception (a
    numpy shape error, a KeyError) is a bug and shows as one."""
    return any(c.__module__.split(".")[0] in PROJECT_PACKAGES for c in type(exc).__mro__)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; only the chosen subcommand's module is imported (``bsc --help`` imports none)."""
    from gateway import __version__

    argv = sys.argv[1:] if argv is None else argv
    chosen = next((a for a in argv if a in COMMANDS), None)

    parser = argparse.ArgumentParser(
        prog="bsc",
        description="Base Sensor Control gateway: actual joint torques and thruster wrench of a "
                    "space robot from its base F/T sensors, IMU and encoders.")
    parser.add_argument("--version", action="version", version=f"bsc {__version__}")
    parser.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_) in COMMANDS.items():
        p = sub.add_parser(name, help=help_, description=help_)
        p.add_argument("--debug", action="store_true", default=argparse.SUPPRESS,
                       help="show tracebacks on errors")
        p.set_defaults(_module=module)
        if name == chosen:
            _load(module).add_arguments(p)
    return parser


# a library error's ``option`` (gateway.errors) -> the flag that sets it, on the commands that have it
OPTION_FLAGS = {"robot": "--robot", "start": "--start", "duration": "--duration", "rate": "--rate",
                "can_ids": "--can-id", "channels": "--channel", "topics": "--topic", "check": "--check",
                "bus_map": "--bus", "fd": "--fd"}


def _load(module: str):
    return importlib.import_module(module if "." in module else f"gateway.commands.{module}")


def main(argv: list[str] | None = None) -> int:
    # Skinny matrix products run far slower with BLAS threads on 2 cores; set before numpy loads.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    try:
        return int(_load(args._module).run(args) or 0)
    except KeyboardInterrupt:
        print("bsc: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except Exception as exc:  # noqa: BLE001 - the one place that turns errors into a line
        if args.debug:
            raise
        if is_project_error(exc) or isinstance(exc, OSError):
            hint = " (--force replaces it)" if isinstance(exc, FileExistsError) and "force" in args else ""
            flag = OPTION_FLAGS.get(getattr(exc, "option", None) or "")
            if flag and flag.lstrip("-").replace("-", "_") in args:
                hint += f" [{flag}]"          # the library names the parameter; the command, its flag
            print(f"bsc {args.command}: error: {exc}{hint}", file=sys.stderr)
            return EXIT_USAGE
        # anything else is a bug, not a bad input: say so
        print(f"bsc {args.command}: internal error: {type(exc).__name__}: {exc} (a bug in bsc: "
              f"--debug shows where)", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    # ``python -m gateway.cli``: this file runs as __main__, a second copy of the module whose
    # UserError the commands (importing gateway.cli) do not raise; use the one they import
    from gateway.cli import main as _main

    raise SystemExit(_main())
