"""Fixtures for the recording tests: leak check, tiny filesystems, the CLI as a subprocess."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(autouse=True)
def no_leaked_recorder_threads():
    """Fail a test that leaves a recorder writer thread running (a Recorder not closed)."""
    yield
    leaked = [t.name for t in threading.enumerate() if t.name.startswith("recorder:")]
    assert not leaked, f"recorder threads still running: {leaked}"


def _mount_tmpfs(path: Path, options: str) -> bool:
    path.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        return False
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(path)],
                          capture_output=True, text=True)
    return proc.returncode == 0


@pytest.fixture
def tiny_fs(tmp_path):
    """A 256 KiB tmpfs, to fill up; skipped where mounting is not permitted."""
    mnt = tmp_path / "tiny"
    if not _mount_tmpfs(mnt, "size=256k"):
        pytest.skip("cannot mount a tmpfs here (needs root / CAP_SYS_ADMIN) to simulate a full disk")
    yield mnt
    subprocess.run(["umount", str(mnt)], check=True)


@pytest.fixture
def read_only_dir(tmp_path):
    """A directory nobody can create files in: a read-only tmpfs when root (root ignores
    permission bits), else a chmod 0555 directory."""
    ro = tmp_path / "ro"
    if os.geteuid() == 0:
        if not _mount_tmpfs(ro, "ro,size=64k"):
            pytest.skip("running as root and cannot mount a read-only tmpfs")
        yield ro
        subprocess.run(["umount", str(ro)], check=True)
    else:
        ro.mkdir()
        ro.chmod(0o555)
        yield ro
        ro.chmod(0o755)


@pytest.fixture(scope="session")
def bsc():
    """Run ``bsc ARGS...`` as a subprocess; returns the CompletedProcess (text)."""
    base = [sys.executable, "-m", "gateway.cli"]
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1",
               PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))

    def run(*args: str, timeout: float = 60):
        return subprocess.run([*base, *map(str, args)], capture_output=True, text=True,
                              cwd=REPO, env=env, timeout=timeout)

    return run
