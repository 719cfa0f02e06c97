"""Write the settings page of the docs site from ``app.config.Settings`` (one table, never written twice).

.venv/bin/python scripts/settings_doc.py            # writes docs/settings.md
.venv/bin/python scripts/settings_doc.py --check    # exit 1 when docs/settings.md is out of date
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

PAGE = Path(__file__).resolve().parents[1] / "docs" / "settings.md"

HEADER = """# Settings

Environment variables (or a `.env` file in the working directory), or `key = value` lines of a settings
file (`hrc study --settings FILE`, `hrc serve --settings FILE`; `hrc tune` writes one) with the names
below in lower case without `HRC_`; a file's values take precedence over the environment. An unknown key or
a bad value stops the command with the key and the reason; an unknown `HRC_` variable is a warning that
names the nearest setting (an error with `HRC_STRICT_SETTINGS=true`). This page is generated from
`app.config.Settings` by `scripts/settings_doc.py`.

| variable | default | meaning |
|---|---|---|
"""


def _default(field: object) -> str:
    value = getattr(field, "default", None)
    if value is None:
        return "none"
    if isinstance(value, float):
        return f"`{value:.4g}`"
    if isinstance(value, Path):
        return f"`{value}`"
    return f"`{str(value).lower() if isinstance(value, bool) else value}`"


def render() -> str:
    from app.config import Settings

    rows = []
    for name, field in Settings.model_fields.items():
        meaning = (field.description or "").replace("|", "\\|").replace("\n", " ")
        rows.append(f"| `HRC_{name.upper()}` | {_default(field)} | {meaning} |")
    return HEADER + "\n".join(rows) + "\n"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only check that the page is up to date")
    args = ap.parse_args()
    text = render()
    if args.check:
        if not PAGE.exists() or PAGE.read_text() != text:
            print(f"{PAGE} is out of date: run scripts/settings_doc.py", file=sys.stderr)
            return 1
        return 0
    PAGE.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
