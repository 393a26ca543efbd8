"""One error tree: every exception class a package defines derives from that package's root (and
from the builtin it mixes in), and the command line tells the two kinds apart: a project error is
one line and exit status 2, anything else is a bug (exit status 1) and says so."""
from __future__ import annotations

import importlib
import inspect
import pkgutil

import pytest

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
    from gateway.mcaplog import McapFileError

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
