"""The one way the app compiles its numba kernels: cached next to the module, in memory where it cannot be.

``numba.njit(cache=True)`` raises at import time when no cache location is writable (a read-only install and
home directory); :func:`jit` then compiles the kernel in memory on every start and says so once.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import numba

__all__ = ["jit"]

logger = logging.getLogger(__name__)
_warned_no_cache = False


def jit(fn: Callable[..., Any] | None = None, **options: Any) -> Any:
    """``numba.njit(cache=True, **options)``, or in-memory compilation where no cache location is writable.

    Use as ``@jit`` or ``@jit(inline="always", ...)``."""

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
