"""Exception types of the runtime and the study layer that the API maps to HTTP statuses.

Resolved lazily (the API must import without building anything), and tolerant of a layer that is not
installed: a missing type maps to an empty tuple, which an ``except`` clause never matches.
"""

from __future__ import annotations

import importlib
from functools import cache


def _types(*dotted: str) -> tuple[type[BaseException], ...]:
    found: list[type[BaseException]] = []
    for name in dotted:
        module, _, attr = name.rpartition(".")
        try:
            obj = getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError):
            continue
        if isinstance(obj, type) and issubclass(obj, BaseException) and obj not in found:
            found.append(obj)
    return tuple(found)


@cache
def frame_rejected_types() -> tuple[type[BaseException], ...]:
    """A pushed skeleton frame was invalid (``FrameRejected`` of the cell's validation)."""
    return _types("app.cell.validation.FrameRejected", "app.cell.human.FrameRejected")


@cache
def ingest_unavailable_types() -> tuple[type[BaseException], ...]:
    """The runtime takes no pushed frames now (not configured with ``HRC_HUMAN_SOURCE=stream``)."""
    return _types("app.control.runtime.IngestUnavailable", "app.control.runtime.StreamNotConfigured")


@cache
def trial_already_running_types() -> tuple[type[BaseException], ...]:
    """A trial was started while another one runs."""
    return _types("app.control.runtime.TrialAlreadyRunning")
