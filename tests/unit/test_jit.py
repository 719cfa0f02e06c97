"""The app's numba kernels load whatever cache an older version left next to them (:mod:`app.jit`)."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]

KERNEL = """
from typing import NamedTuple

from app.jit import jit


class {name}(NamedTuple):
    a: float


@jit
def twice(p):
    return 2.0 * p.a


print(twice({name}(1.5)))
"""


def _run(module_dir: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(module_dir), str(REPO_ROOT)])}
    env.pop("NUMBA_CACHE_DIR", None)  # the cache next to the module, as the app's kernels have it
    return subprocess.run(
        [sys.executable, "-c", "import kernel_under_test"],
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


def test_a_cache_that_names_a_renamed_type_is_recompiled_not_an_error(tmp_path: Path) -> None:
    """numba unpickles a cache's index before it checks the source: an index naming a type that a newer
    version renamed stopped the kernel (``Can't get attribute 'Params'``) until the cache was deleted."""
    module = tmp_path / "kernel_under_test.py"
    module.write_text(textwrap.dedent(KERNEL.format(name="Params")))
    first = _run(tmp_path)
    assert first.returncode == 0 and first.stdout.strip() == "3.0", first.stderr
    assert list((tmp_path / "__pycache__").glob("kernel_under_test.twice-*.nbi")), "no cache was written"
    # the same kernel on the same line, its argument's type renamed: the old index names "Params"
    module.write_text(textwrap.dedent(KERNEL.format(name="KernelParams")))
    second = _run(tmp_path)
    assert second.returncode == 0 and second.stdout.strip() == "3.0", second.stderr
    assert "Can't get attribute" not in second.stderr
