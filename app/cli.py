"""The ``hrc`` command line.

Every sub-command imports what it needs inside its body, so ``hrc --help`` stays fast and a missing
optional piece only affects the command that uses it.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
from typing import Annotated

import typer

app = typer.Typer(
    name="hrc",
    help="Proactive human-aware motion planning for a UR5e working beside a person.",
    no_args_is_help=True,
    add_completion=False,
)


@app.callback()
def _root() -> None:
    """Proactive human-aware motion planning for a UR5e working beside a person."""


def _bench_names() -> list[str]:
    import app.bench as bench_pkg

    return sorted(m.name for m in pkgutil.iter_modules(bench_pkg.__path__) if not m.name.startswith("_"))


@app.command()
def bench(
    name: Annotated[str, typer.Argument(help="Benchmark to run (see `hrc bench --list`).")] = "",
    as_json: Annotated[bool, typer.Option("--json", help="Print one JSON object and nothing else.")] = False,
    quick: Annotated[bool, typer.Option("--quick", help="Fewer repetitions (smoke run).")] = False,
    list_: Annotated[bool, typer.Option("--list", help="List the benchmarks and exit.")] = False,
) -> None:
    """Run a benchmark; it prints its measurements (medians and p95 over many runs) as JSON."""
    names = _bench_names()
    if list_ or not name:
        typer.echo("\n".join(names))
        raise typer.Exit(0)
    if name not in names:
        raise typer.BadParameter(f"unknown benchmark {name!r}; choose one of: {', '.join(names)}")
    module = importlib.import_module(f"app.bench.{name}")
    result = module.run(quick=quick, progress=not as_json)
    typer.echo(json.dumps(result, indent=None if as_json else 2, sort_keys=False))


def main() -> None:
    """Console entry point."""
    app()


if __name__ == "__main__":
    main()
