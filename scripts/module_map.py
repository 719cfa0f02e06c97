#!/usr/bin/env python
"""Write the module map of ``docs/architecture.md`` from the tree: every module of ``app`` with its size and
the first paragraph of its docstring. ``tests/unit/test_layout.py`` checks that the map lists exactly the
modules that exist, so run this after moving, adding or removing a module::

    .venv/bin/python scripts/module_map.py
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "architecture.md"
BEGIN, END = "<!-- module map: begin -->", "<!-- module map: end -->"


def modules() -> list[tuple[str, int, str]]:
    out = []
    for path in sorted((ROOT / "app").rglob("*.py")):
        if "migrations" in path.parts:
            continue
        text = path.read_text()
        doc = ast.get_docstring(ast.parse(text)) or ""
        first = " ".join(doc.split("\n\n")[0].split()).replace("|", "\\|")
        out.append((path.relative_to(ROOT).as_posix(), len(text.splitlines()), first))
    return out


def table() -> str:
    rows = ["| module | lines | what it is |", "|---|---|---|"]
    rows += [f"| `{m}` | {n} | {doc} |" for m, n, doc in modules()]
    return "\n".join(rows)


def main() -> int:
    text = DOC.read_text()
    if BEGIN not in text or END not in text:
        print(f"{DOC} has no {BEGIN} ... {END} section", file=sys.stderr)
        return 1
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    DOC.write_text(f"{head}{BEGIN}\n{table()}\n{END}{tail}")
    print(f"wrote {len(modules())} modules into {DOC.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
