"""Opening a robot's CAN buses on any python-can adapter: bit rates and adapter arguments.

Every command that opens a bus (``bsc gateway``, ``bsc record``, ``bsc replay --interface``,
``bsc sim --interface``) takes ``-b/--bitrate``, ``--data-bitrate`` (CAN FD data phase) and
``--bus-kwarg KEY=VALUE`` (any other argument of the interface's bus class: a serial number,
an application name, a timing register, ...). What a bus is opened with, key by key:

1. the command's flags (``--bitrate``, ``--data-bitrate``, ``--bus-kwarg``, and what the command
   itself sets: the channel, ``fd``, a UDP port);
2. python-can's own configuration: its config file (``~/.canrc``, ``can.ini``, ...; the
   section named by ``--bus-kwarg config_context=NAME``, else ``[default]``) and its
   ``CAN_BITRATE`` / ``CAN_CONFIG`` environment variables;
3. the robot's wire: :data:`drivers.wire.BITRATE` (1 Mbit/s, the DBC's) and, on CAN FD,
   :data:`drivers.wire.FD_DATA_BITRATE`, unless a bit timing (``timing``, ``f_clock``...) is
   configured instead.

The drivers themselves are given their buses, never open one (any interface swaps in); this is
what the commands and the simulated firmware open them with.

Interfaces whose bit rate the operating system sets (socketcan: ``ip link set can0 type can
bitrate 1000000``) ignore it; the virtual and UDP interfaces have none.
"""
from __future__ import annotations

import argparse
import dataclasses
import re
from collections.abc import Iterable, Mapping
from typing import TYPE_CHECKING, Any

from drivers.errors import DriverError

if TYPE_CHECKING:
    import can


class BusOptionsError(DriverError, ValueError):
    """Bus options that do not go together (a data bit rate without CAN FD, options without a bus)."""


_RATE = re.compile(r"^\s*([0-9]+(?:\.[0-9]+)?)\s*([kKmM]?)\s*(?:bit/s|bps|b/s)?\s*$")
# keys that mean the bit timing is given some other way than a bit rate
_TIMING_KEYS = ("timing", "f_clock", "f_clock_mhz", "brp", "nom_brp", "btr0", "btr1")


def bitrate(text: str) -> int:
    """``1000000``, ``1M``, ``500k``, ``2.5M`` -> bits per second (argparse type)."""
    m = _RATE.match(str(text))
    if not m:
        raise argparse.ArgumentTypeError(f"{text!r}: a bit rate such as 1000000, 1M or 500k")
    value = float(m.group(1)) * {"": 1, "k": 1e3, "m": 1e6}[m.group(2).lower()]
    if value != int(value) or not 0 < value <= 20_000_000:
        raise argparse.ArgumentTypeError(f"{text!r}: bit rates are whole bit/s up to 20 Mbit/s")
    return int(value)


def _value(text: str) -> Any:
    """A ``--bus-kwarg`` value: an int, a float, true/false, none, else the string."""
    low = text.strip().lower()
    if low in ("true", "false"):
        return low == "true"
    if low in ("none", "null"):
        return None
    try:
        return int(text, 0)
    except ValueError:
        pass
    try:
        return float(text)
    except ValueError:
        return text


def bus_kwarg(text: str) -> tuple[str, Any]:
    """``KEY=VALUE`` (argparse type)."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not key.isidentifier():
        raise argparse.ArgumentTypeError(f"{text!r}: expected KEY=VALUE, e.g. serial=12345")
    if key in ("interface", "channel", "bustype"):
        raise argparse.ArgumentTypeError(f"{text!r}: give the {key} with --interface/--channel")
    return key, _value(value)


CHANNEL_HELP = "channel prefix (<prefix>-<bus>), or BUS=CHANNEL for each bus (repeatable)"


def add_can_arguments(group: argparse._ActionsContainer, *,
                      interface_help: str | None = "python-can interface: socketcan, udp_multicast, "
                      "pcan, kvaser, vector, virtual, ...", channel_help: str = CHANNEL_HELP,
                      fd_help: str = "the buses run CAN FD (same frames, bit-rate switch)") -> None:
    """The CAN options of every command that opens a robot's buses, on ``group`` (an argparse
    group): ``-i/--interface`` (unless ``interface_help`` is None: the command places it itself),
    ``-c/--channel``, ``--fd``, ``-b/--bitrate``, ``--data-bitrate``, ``--bus-kwarg``. Nothing
    has a default here (``None``, ``[]``, ``False``): the command decides, or its configuration."""
    if interface_help is not None:
        group.add_argument("--interface", "-i", default=None, metavar="NAME", help=interface_help)
    group.add_argument("--channel", "-c", action="append", default=[], metavar="PREFIX|BUS=CHANNEL",
                       help=channel_help)
    group.add_argument("--fd", action="store_true", help=fd_help)
    add_bus_arguments(group)


def add_bus_arguments(group: argparse._ActionsContainer) -> None:
    """``-b/--bitrate``, ``--data-bitrate`` and ``--bus-kwarg`` on a command that opens buses."""
    from drivers.wire import BITRATE, FD_DATA_BITRATE

    group.add_argument("--bitrate", "-b", type=bitrate, default=None, metavar="BPS",
                       help=f"nominal bit rate of every bus, e.g. 1M, 500k (default: python-can's configuration, "
                            f"else the DBC's {BITRATE / 1e6:g} Mbit/s; socketcan takes it from ip link)")
    group.add_argument("--data-bitrate", type=bitrate, default=None, metavar="BPS",
                       help=f"CAN FD data-phase bit rate, with --fd (default: python-can's configuration, "
                            f"else {FD_DATA_BITRATE / 1e6:g} Mbit/s)")
    group.add_argument("--bus-kwarg", type=bus_kwarg, action="append", default=[], metavar="KEY=VALUE",
                       help="any other argument of the python-can bus (repeatable), e.g. serial=12345, "
                            "app_name=CANalyzer, config_context=robot (a section of python-can's config file)")


@dataclasses.dataclass(frozen=True)
class BusOptions:
    """What the user asked of every bus a command opens (see the module docstring)."""

    bitrate: int | None = None
    data_bitrate: int | None = None
    extra: tuple[tuple[str, Any], ...] = ()

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> "BusOptions":
        return cls(getattr(args, "bitrate", None), getattr(args, "data_bitrate", None),
                   tuple(getattr(args, "bus_kwarg", None) or ()))

    def kwargs(self, interface: str, channel: str, *, fd: bool = False,
               fixed: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """The keyword arguments of ``can.Bus(..., ignore_config=True)``: the flags over
        ``fixed`` (the command's own), over python-can's configuration, over the wire's rates."""
        import can

        given: dict[str, Any] = dict(fixed or {})
        extra = dict(self.extra)
        context = extra.pop("config_context", None)
        given.update(extra)
        given.update(interface=interface, channel=channel)
        if fd:
            given["fd"] = True
        if self.bitrate is not None:
            given["bitrate"] = self.bitrate
        if self.data_bitrate is not None:
            given["data_bitrate"] = self.data_bitrate
        cfg = dict(can.util.load_config(config=given, context=context))
        if not any(cfg.get(k) is not None for k in _TIMING_KEYS):
            from drivers.wire import BITRATE, FD_DATA_BITRATE

            if cfg.get("bitrate") is None:
                cfg["bitrate"] = BITRATE
            if cfg.get("fd") and cfg.get("data_bitrate") is None:
                cfg["data_bitrate"] = FD_DATA_BITRATE
        return cfg

    def check(self, fd: bool) -> None:
        if self.data_bitrate is not None and not fd:
            raise BusOptionsError("a data bit rate is the CAN FD data phase: the buses must run CAN FD", option="fd")


def open_bus(interface: str, channel: str, options: BusOptions | None = None, *, fd: bool = False,
             **fixed: Any) -> can.BusABC:
    """``can.Bus`` of ``interface``/``channel`` with :meth:`BusOptions.kwargs` (python-can's
    configuration read once, here)."""
    import can

    kw = (options or BusOptions()).kwargs(interface, channel, fd=fd, fixed=fixed)
    kw.pop("interface", None)
    kw.pop("channel", None)
    return can.Bus(interface=interface, channel=channel, ignore_config=True, **kw)


def describe(options: BusOptions | None, interface: str, channels: Iterable[str], *, fd: bool = False) -> str:
    """``bitrate 1000000`` (and the data bit rate) that the first bus opens with, for a start-up line."""
    try:
        kw = (options or BusOptions()).kwargs(interface, next(iter(channels)), fd=fd)
    except Exception:  # noqa: BLE001 - only a description
        return ""
    out = f"bitrate {kw.get('bitrate')}" if kw.get("bitrate") else "bit timing as configured"
    if kw.get("data_bitrate"):
        out += f", data bitrate {kw['data_bitrate']}"
    return out
