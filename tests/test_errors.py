"""One error tree: every exception class a package defines derives from that package's root (and
from the builtin it mixes in), and the command line tells the two kinds apart: a project error is
one line and exit status 2, anything else is a bug (exit status 1) and says so."""
from __future__ import annotations

import ast
import importlib
import inspect
import pkgutil
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ROOTS = {"gateway": ("gateway.errors", "GatewayError"), "drivers": ("drivers.errors", "DriverError"),
         "simulator": ("simulator.errors", "SimulatorError"),
         "robot_description": ("robot_description.errors", "DescriptionError")}


def _error_classes(package: str):
    pkg = importlib.import_module(package)
    names = [package] + [i.name for i in pkgutil.walk_packages(pkg.__path__, package + ".")]
    for name in names:
        if name.endswith("__main__"):
            continue
        mod = importlib.import_module(name)
        for _, obj in inspect.getmembers(mod, inspect.isclass):
            if issubclass(obj, BaseException) and obj.__module__ == mod.__name__:
                yield obj


@pytest.mark.parametrize("package", list(ROOTS))
def test_every_error_of_a_package_derives_from_its_root(package):
    module, name = ROOTS[package]
    root = getattr(importlib.import_module(module), name)
    classes = [c for c in _error_classes(package) if c is not root]
    assert len(classes) >= 2
    assert [c.__qualname__ for c in classes if not issubclass(c, root)] == []


def test_a_project_error_is_one_line_anything_else_is_a_bug(monkeypatch, capsys):
    from gateway import cli
    from gateway.log.errors import McapFileError

    class Command:
        def __init__(self, exc):
            self.exc = exc

        def add_arguments(self, parser):
            pass

        def run(self, args):
            raise self.exc

    monkeypatch.setattr(cli, "_load", lambda module: Command(McapFileError("x.mcap: not an MCAP file")))
    assert cli.main(["info"]) == cli.EXIT_USAGE
    assert capsys.readouterr().err == "bsc info: error: x.mcap: not an MCAP file\n"
    monkeypatch.setattr(cli, "_load", lambda module: Command(ValueError("operands could not be broadcast")))
    assert cli.main(["info"]) == cli.EXIT_FAILURE
    err = capsys.readouterr().err
    assert err.startswith("bsc info: internal error: ValueError: operands could not be broadcast") and "bug" in err


FLAG = re.compile(r"(?<![\w-])--[a-z][a-z-]*")
CLI_MODULES = ("gateway/commands/", "harness/commands/", "gateway/cli.py")


def _flags_in_raises(path: Path) -> list[str]:
    """``file:line: --flag`` for each command-line flag in a message a library ``raise`` builds
    (argparse's ArgumentTypeError is the command line's own)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if not (isinstance(node, ast.Raise) and isinstance(node.exc, ast.Call)):
            continue
        func = node.exc.func
        if (func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")) == "ArgumentTypeError":
            continue
        for arg in node.exc.args:
            for sub in ast.walk(arg):
                if isinstance(sub, ast.Constant) and isinstance(sub.value, str):
                    out += [f"{path.relative_to(ROOT)}:{node.lineno}: {m}" for m in FLAG.findall(sub.value)]
    return out


def test_library_messages_name_no_command_line_flag():
    """A library error says what is wrong in its own terms; the command line adds its flag
    (gateway.errors ``option``, gateway.cli)."""
    found = []
    for package in ROOTS:
        for path in sorted((ROOT / package).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            if not rel.startswith(CLI_MODULES):
                found += _flags_in_raises(path)
    assert found == [], "\n".join(found)


def test_the_flag_check_finds_a_flag(tmp_path):
    bad = ROOT / "gateway" / "_flag_probe.py"
    try:
        bad.write_text('def f():\n    raise ValueError(f"--start {1}: must be >= 0")\n')
        assert _flags_in_raises(bad) == ["gateway/_flag_probe.py:2: --start"]
    finally:
        bad.unlink()


def test_the_cli_names_the_flag_of_the_option_at_fault(tmp_path, capsys):
    from gateway.cli import main

    assert main(["replay", str(tmp_path / "x.mcap"), "--out", str(tmp_path / "o"), "--can-id", "zz"]) == 2
    err = capsys.readouterr().err
    assert err == "bsc replay: error: CAN id 'zz': not an integer (hex as 0x200) [--can-id]\n"
