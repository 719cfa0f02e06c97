"""Command groups of ``hrc`` that are registered in :mod:`app.cli`: ``hrc hmp ...`` and ``hrc cell ...``.

They live here, above the packages they drive, so that the pure core (:mod:`app.prediction`) and the cell
(:mod:`app.cell`) import no command line and nothing above themselves.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NoReturn

import typer

if TYPE_CHECKING:
    from app.config import Settings, WorkCell

__all__ = ["fail", "load_settings", "load_workcell_or_fail"]


def fail(message: str, *, code: int = 2) -> NoReturn:
    """Print ``error: message`` as one plain line on stderr and exit with ``code``.

    For errors a person can act on (a missing file, an invalid field): no traceback, and no panel that a
    narrow terminal would cut or fold (the message is never truncated, whatever the terminal's width or
    the length of a path in it)."""
    typer.echo("error: " + " ".join(line.strip() for line in str(message).splitlines()), err=True)
    raise typer.Exit(code)


def load_settings(**overrides: Any) -> Settings:
    """``Settings(**overrides)`` (environment and ``.env`` below them), or :func:`fail` naming the variable
    and the reason."""
    from pydantic import ValidationError

    from app.config import ENV_PREFIX, Settings

    try:
        return Settings(**overrides)
    except ValidationError as exc:
        msgs = "; ".join(
            f"{ENV_PREFIX}{'.'.join(map(str, e['loc'])).upper()}: {e['msg']}" for e in exc.errors()
        )
        fail(f"invalid settings: {msgs}")


def load_workcell_or_fail(settings: Settings) -> WorkCell:
    """The settings' work cell, or :func:`fail` with the file, the field and the reason (one line)."""
    from app.config import WorkCellError

    try:
        return settings.load_workcell()
    except WorkCellError as exc:
        fail(f"{exc} (HRC_WORKCELL)")
