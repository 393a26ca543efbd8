"""The house's checks, as the test suite runs them: the layering of the tree as import-linter
checks it (contracts in pyproject.toml: the product (drivers, gateway) never imports the
simulator or the harness, the drivers never the gateway, the simulator never the gateway, the
session log's format (gateway.log) runs no part of the gateway; a
deployment beside a real robot runs the product alone), ruff's lint, and mypy's strict types on the
drivers and the estimator (all three configured in pyproject.toml)."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def tool(name: str, *args: str) -> subprocess.CompletedProcess:
    """A console script of this environment's (the test extras install it)."""
    exe = shutil.which(name, path=str(Path(sys.executable).parent)) or name
    return subprocess.run([exe, *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def lint_imports(*args: str) -> subprocess.CompletedProcess:
    return tool("lint-imports", "--no-cache", *args)


def test_the_layering_contracts_are_kept():
    out = lint_imports()
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "Contracts: 4 kept, 0 broken." in out.stdout


def test_a_broken_contract_is_caught(tmp_path):
    """The check can fail: the harness does import the gateway, so this contract must break."""
    cfg = tmp_path / "contracts.toml"
    cfg.write_text('[tool.importlinter]\nroot_packages = ["gateway", "harness", "simulator", "drivers", '
                   '"robot_description"]\n\n[[tool.importlinter.contracts]]\nname = "harness alone"\n'
                   'type = "forbidden"\nsource_modules = ["harness"]\nforbidden_modules = ["gateway"]\n')
    out = lint_imports("--config", str(cfg))
    assert out.returncode == 1 and "harness alone BROKEN" in out.stdout, out.stdout[-2000:]


def test_ruff_finds_nothing():
    out = tool("ruff", "check", "--no-cache", ".")
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-1000:]


def test_ruff_would_catch_an_unused_import(tmp_path):
    """The check can fail: the same configuration on a file with an unused import."""
    bad = tmp_path / "bad.py"
    bad.write_text("import os\n")
    out = tool("ruff", "check", "--no-cache", "--config", str(ROOT / "pyproject.toml"), str(bad))
    assert out.returncode == 1 and "F401" in out.stdout, out.stdout


def test_mypy_strict_finds_nothing():
    """mypy --strict on the files [tool.mypy] names (the drivers and the estimator)."""
    out = tool("mypy")
    assert out.returncode == 0, out.stdout[-4000:] + out.stderr[-1000:]


def test_mypy_would_catch_a_type_error(tmp_path):
    """The check can fail: the same configuration on a file with an untyped def and a wrong return type."""
    bad = tmp_path / "bad.py"
    bad.write_text("def untyped(x):\n    return x\n\n\ndef one() -> int:\n    return 'one'\n")
    out = tool("mypy", "--config-file", str(ROOT / "pyproject.toml"), str(bad))
    assert out.returncode == 1, out.stdout + out.stderr
    assert "[no-untyped-def]" in out.stdout and "[return-value]" in out.stdout, out.stdout
