#!/usr/bin/env bash
# The whole test suite from a fresh clone: set up, lint, format check, then pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
scripts/system-deps.sh
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# the documentation site: the settings page generated from the code, every page built with warnings as errors
.venv/bin/python scripts/settings_doc.py --check
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --quiet
set +e
.venv/bin/python -m pytest "$@"
rc=$?
set -e
# pytest exits 5 when it collected no test: that is a failure of the suite, say so.
if [ "$rc" -eq 5 ]; then
  echo "pytest collected no tests" >&2
fi
exit "$rc"
