"""numba's cache directory is named after the kernels' sources (drivers/jitcache.py)."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from drivers import jitcache


def _tree(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def test_the_key_follows_every_kernel_source_and_nothing_else(tmp_path, monkeypatch):
    _tree(tmp_path, {"drivers/kernel.py": "from numba import njit\n", "gateway/estimator/core.py": "import numba\n",
                     "gateway/cli.py": "print('no kernels here')\n"})
    monkeypatch.setattr(jitcache, "_ROOT", tmp_path)
    key = jitcache.sources_key()
    assert len(key) == 16 and jitcache.sources_key() == key
    (tmp_path / "gateway/cli.py").write_text("print('still none')\n")
    assert jitcache.sources_key() == key                  # not a kernel: the cache stays
    # an edit of a kernel that another one calls (core.py inlines chain_kernel's functions):
    # numba's own cache would not notice it, the directory changes
    _tree(tmp_path, {"gateway/estimator/chain_kernel.py": "from numba import njit  # v1\n"})
    k1 = jitcache.sources_key()
    (tmp_path / "gateway/estimator/chain_kernel.py").write_text("from numba import njit  # v2\n")
    assert len({key, k1, jitcache.sources_key()}) == 3


def test_the_directory_is_set_once_per_sources_and_children_keep_it(tmp_path):
    saved = {k: os.environ.get(k) for k in ("NUMBA_CACHE_DIR", "BSC_NUMBA_CACHE_KEY", "XDG_CACHE_HOME")}
    from numba.core import config

    try:
        os.environ.pop("BSC_NUMBA_CACHE_KEY", None)
        os.environ["NUMBA_CACHE_DIR"] = str(tmp_path / "base")
        cache = jitcache.configure()
        key = jitcache.sources_key()
        assert cache == str(tmp_path / "base" / key) == os.environ["NUMBA_CACHE_DIR"]
        assert jitcache.configure() == cache              # again (a child process): the same place
        assert config.CACHE_DIR == cache                  # numba was imported already: it re-read it
        out = subprocess.run([sys.executable, "-c", "import gateway, os; print(os.environ['NUMBA_CACHE_DIR'])"],
                             capture_output=True, text=True, check=True, env=dict(os.environ))
        assert out.stdout.strip() == cache
        del os.environ["NUMBA_CACHE_DIR"], os.environ["BSC_NUMBA_CACHE_KEY"]
        os.environ["XDG_CACHE_HOME"] = str(tmp_path / "xdg")
        assert jitcache.configure() == str(tmp_path / "xdg" / "bsc" / "numba" / key)
    finally:                                              # the rest of the session keeps its cache
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        config.reload_config()


def test_old_caches_of_other_sources_are_removed(tmp_path):
    import time

    key = "0123456789abcdef"
    old, recent, other = tmp_path / "fedcba9876543210", tmp_path / "00000000000000aa", tmp_path / "notes"
    for d in (old, recent, other, tmp_path / key):
        d.mkdir()
    stale = time.time() - (jitcache.KEEP_DAYS + 1) * 86400
    for d in (old, other, tmp_path / key):
        os.utime(d, (stale, stale))
    jitcache._prune(tmp_path, key)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([recent.name, other.name, key])
