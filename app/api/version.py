"""The installed version of the application, reported by the API (``/api/health``, ``/api/info``, OpenAPI)."""

from __future__ import annotations


def app_version() -> str:
    """The version of the installed ``hrc-proactive`` distribution; ``0.0.0`` when it is not installed."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("hrc-proactive")
    except PackageNotFoundError:
        return "0.0.0"
