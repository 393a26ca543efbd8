"""Where numba keeps its compiled kernels: a directory named after the kernels' sources.

numba's own cache invalidates a compiled function when the file that defines it changes, but not
when a function it calls from another file does: the estimator's entry points in
``gateway/estimator/core.py`` compile ``chain_kernel``'s, ``joint_filter``'s, ``fdi``'s and
``thruster_kernel``'s functions into themselves, so after an edit (or a ``git pull``) of one of
those alone, the cache would go on serving the old arithmetic. Here the cache directory carries a
hash of every source file of ``drivers/`` and ``gateway/`` that uses numba: any change to any of
them compiles everything afresh (about a minute, ``python -m gateway.engine.warm``), and a cache
can never mix kernels of two versions.

:func:`configure` runs when ``drivers`` or ``gateway`` is imported, before numba is: it sets
``NUMBA_CACHE_DIR`` to ``BASE/<hash>``, BASE being ``NUMBA_CACHE_DIR`` if the user set one, else
``${XDG_CACHE_HOME:-~/.cache}/bsc/numba``. Child processes inherit the final directory. The
caches of other sources left there are removed once unused for :data:`KEEP_DAYS` days.
"""
from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

_ROOT = Path(__file__).resolve().parent.parent
_PACKAGES = ("drivers", "gateway")
_KEY_ENV = "BSC_NUMBA_CACHE_KEY"
KEEP_DAYS = 14          # another version's cache unused this long is removed


def sources_key() -> str:
    """16 hex digits: a hash of the path and bytes of every ``.py`` file under ``drivers/`` and
    ``gateway/`` that mentions numba, in sorted order."""
    h = hashlib.sha256()
    for pkg in _PACKAGES:
        for path in sorted((_ROOT / pkg).rglob("*.py")):
            data = path.read_bytes()
            if b"numba" in data:
                h.update(str(path.relative_to(_ROOT)).encode())
                h.update(len(data).to_bytes(8, "little"))
                h.update(data)
    return h.hexdigest()[:16]


def configure() -> str:
    """Set ``NUMBA_CACHE_DIR`` for this process and its children; returns it."""
    key = sources_key()
    current = os.environ.get("NUMBA_CACHE_DIR")
    if current and os.environ.get(_KEY_ENV) == key and Path(current).name == key:
        return current                              # set by a parent process of the same sources
    if current and os.environ.get(_KEY_ENV) and Path(current).name == os.environ[_KEY_ENV]:
        current = str(Path(current).parent)         # a parent's, of other sources: its base
    default = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "bsc" / "numba"
    base = Path(current) if current else default
    cache = str(base / key)
    _prune(base, key)
    os.environ["NUMBA_CACHE_DIR"] = cache
    os.environ[_KEY_ENV] = key
    if "numba" in sys.modules:                      # imported before us: make it read the setting again
        from numba.core import config

        config.reload_config()                      # type: ignore[no-untyped-call]
    return cache


def _prune(base: Path, key: str) -> None:
    """Remove the caches of other sources that nothing has written to for :data:`KEEP_DAYS` days
    (every edit of a kernel leaves one behind, ~20 MB each); never this one, never anything but a
    directory named like a key. Best effort: a cache another process removes first is no error."""
    import shutil
    import time

    try:
        entries = list(base.iterdir())
    except OSError:
        return
    cutoff = time.time() - KEEP_DAYS * 86400
    for d in entries:
        name = d.name
        if name == key or len(name) != 16 or any(c not in "0123456789abcdef" for c in name):
            continue
        try:
            if d.is_dir() and d.stat().st_mtime < cutoff:
                shutil.rmtree(d, ignore_errors=True)
        except OSError:
            pass
