"""The one way the app compiles its numba kernels: cached next to the module, in memory where it cannot be.

``numba.njit(cache=True)`` raises at import time when no cache location is writable (a read-only install and
home directory); :func:`jit` then compiles the kernel in memory on every start and says so once.

A cache written by an older version of the app is recompiled, never an error: numba unpickles a cache's
index before it checks that the index belongs to the source it caches, so an index that names a type since
renamed or moved (``Can't get attribute ...``) would stop the kernel from loading at all; importing this
module makes numba treat such an index as stale (:func:`_tolerate_foreign_cache_indexes`).

Every kernel releases the interpreter lock while it runs (``nogil``; none touches a Python object): the live
runtime's threads (the robot command loop, the frame thread, the planner pool) share one interpreter, and a
kernel of one need not hold up the others.
"""

from __future__ import annotations

import logging
import pickle
from collections.abc import Callable
from typing import Any

import numba
from numba.core import caching

__all__ = ["jit"]

logger = logging.getLogger(__name__)
_warned_no_cache = False


def _tolerate_foreign_cache_indexes() -> None:
    """Make numba's cache index loader return an empty index (recompile) instead of raising where the index
    cannot be unpickled with the present code. Does nothing where numba has no such loader."""
    cls = getattr(caching, "IndexDataCacheFile", None)
    load = getattr(cls, "_load_index", None)
    if cls is None or load is None or getattr(load, "tolerant", False):
        return

    def _load_index(self: Any) -> dict[Any, Any]:
        try:
            return load(self)
        except (AttributeError, ImportError, pickle.UnpicklingError, EOFError, TypeError, ValueError) as exc:
            logger.info("numba cache %s is of other code (%s); compiling anew", self._index_path, exc)
            return {}

    _load_index.tolerant = True  # type: ignore[attr-defined]
    cls._load_index = _load_index


_tolerate_foreign_cache_indexes()


def jit(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit(cache=True, nogil=True, **options)``, or in-memory compilation where no cache location is
    writable.

    Use as ``@jit`` or ``@jit(inline="always", ...)``."""

    options.setdefault("nogil", True)

    def wrap(f: Callable[..., Any]) -> Any:
        global _warned_no_cache
        try:
            return numba.njit(cache=True, **options)(f)
        except RuntimeError as exc:  # numba found no writable cache directory for this file
            if not _warned_no_cache:
                logger.warning("numba kernels compile in memory on every start (no cache location): %s", exc)
                _warned_no_cache = True
            return numba.njit(cache=False, **options)(f)

    return wrap if fn is None else wrap(fn)
