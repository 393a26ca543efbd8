"""The layering of the tree, as import-linter checks it (contracts in pyproject.toml): the
product (drivers, gateway) never imports the simulator or the harness, the drivers never the
gateway, the simulator never the gateway. A deployment beside a real robot runs the product alone."""
from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def lint_imports(*args: str) -> subprocess.CompletedProcess:
    exe = shutil.which("lint-imports", path=str(Path(sys.executable).parent)) or "lint-imports"
    return subprocess.run([exe, "--no-cache", *args], cwd=ROOT, capture_output=True, text=True, timeout=300)


def test_the_layering_contracts_are_kept():
    out = lint_imports()
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-2000:]
    assert "Contracts: 3 kept, 0 broken." in out.stdout


def test_a_broken_contract_is_caught(tmp_path):
    """The check can fail: the harness does import the gateway, so this contract must break."""
    cfg = tmp_path / "contracts.toml"
    cfg.write_text('[tool.importlinter]\nroot_packages = ["gateway", "harness", "simulator", "drivers", '
                   '"robot_description"]\n\n[[tool.importlinter.contracts]]\nname = "harness alone"\n'
                   'type = "forbidden"\nsource_modules = ["harness"]\nforbidden_modules = ["gateway"]\n')
    out = lint_imports("--config", str(cfg))
    assert out.returncode == 1 and "harness alone BROKEN" in out.stdout, out.stdout[-2000:]
