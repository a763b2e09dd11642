"""Where numba keeps flyslam's compiled kernels, and how two variants of one kernel stay apart there.

Every kernel is ``cache=True``: it is compiled once (``python -m common.warmup``, run by deploy/setup.sh)
and loaded from disk by every later process.  Location: numba's own default, the ``__pycache__`` next to
each source file, when that is writable; otherwise ``$XDG_CACHE_HOME/flyslam/numba`` (default
``~/.cache/flyslam/numba``).  An explicit ``NUMBA_CACHE_DIR`` always wins.  ``configure()`` runs when
``common`` is imported, i.e. before any kernel module is decorated (numba picks the place at decoration).
"""
from __future__ import annotations

import os
import sys
import types
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent


def _writable_dir(path: Path) -> bool:
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    return os.access(path, os.W_OK | os.X_OK)


def user_cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "flyslam" / "numba"


def configure() -> str:
    """Choose the cache location (see the module docstring) and return it ('' = next to the sources)."""
    chosen = os.environ.get("NUMBA_CACHE_DIR", "")
    if not chosen and not _writable_dir(PACKAGE_DIR / "__pycache__"):
        chosen = str(user_cache_dir())
        os.environ["NUMBA_CACHE_DIR"] = chosen
        if "numba" in sys.modules:          # numba already read its settings: make it read them again
            from numba.core import config
            config.reload_config()
    return chosen


def cache_twin(fn: types.FunctionType, tag: str) -> types.FunctionType:
    """A copy of ``fn`` under the qualified name ``<name>_<tag>``, to jit a second variant of one source.

    numba's on-disk cache is keyed by the function's name, signature and bytecode but not by its compile
    options, so ``njit(parallel=True)(f)`` and ``njit(parallel=False)(f)`` would load each other's machine
    code (whichever a machine compiled first); a twin with its own name gets its own cache entries."""
    twin = types.FunctionType(fn.__code__, fn.__globals__, f"{fn.__name__}_{tag}", fn.__defaults__,
                              fn.__closure__)
    twin.__qualname__ = f"{fn.__qualname__}_{tag}"
    twin.__module__ = fn.__module__
    twin.__doc__ = fn.__doc__
    return twin


def on_disk(dispatchers) -> bool:
    """Whether numba's cache holds current machine code for each of ``dispatchers`` (an index whose
    source stamp matches), so that a first call loads it rather than compiles.  numba has no public call
    for this; with an API this does not know, True."""
    try:
        return all(len(d._cache._cache_file._load_index()) > 0 for d in dispatchers)
    except AttributeError:
        return True
