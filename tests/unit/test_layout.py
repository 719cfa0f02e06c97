"""The package layout's rules, read from the source with :mod:`ast` (nothing is imported).

- Imports point one way: ``api, ui -> control, study -> cell -> planning, prediction, safety``. The pure
  core (``planning``, ``prediction``, ``safety``) imports nothing from the runtime or the web, nor the web,
  database or viewer libraries; ``cell`` imports nothing from ``control``, ``study``, ``api``, ``ui``; the
  bottom (``config``, ``jit``: the settings, the kernel compiler) imports nothing from ``cell`` or above.
- A package's private parts stay its own: no module imports a ``_``-module or a ``_``-name of another
  top-level package of ``app`` (each package re-exports what the others need from a public module).
- The control code asks the predictor and the human source for what they do (their protocols,
  :class:`app.prediction.forecast.Predictor` and :class:`app.cell.source.HumanSource`) and never probes
  them with ``hasattr``/``getattr``.
- No import circles between the modules of ``app`` (every import counts, also those inside functions:
  a circle through a lazy import is still one concept split in the wrong place).
- Nothing that decides (planner, predictor, safety function, supervisor, anticipation, trial engine)
  imports the simulated operator: it is the simulated *world*. In ``app.control`` only the assembly of a
  trial's world (``app.control.world``, :data:`WORLD`) creates it.
- A numba kernel takes at most 12 parameters (pass NamedTuples of arrays instead of dozens of arrays).
- The plain-NumPy references that check the compiled kernels live in ``reference`` modules that only tests
  and benchmarks import.
- No module of ``app`` is longer than 1,200 lines.

Every other rule holds for every module: there is no list of exceptions.
"""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import app

APP = Path(app.__file__).resolve().parent
MAX_LINES = 1200
MAX_KERNEL_PARAMS = 12
CORE = ("planning", "prediction", "safety")
RUNTIME_AND_WEB = ("control", "cell", "study", "api", "ui", "bench", "cli", "commands")
WEB_DB_VIEW_LIBS = ("fastapi", "starlette", "sqlalchemy", "alembic", "viser", "uvicorn", "multiprocessing")
ABOVE_THE_CELL = ("control", "study", "api", "ui", "bench", "commands", "cli")
# the bottom of the layout: the settings and the kernel compiler, below the cell and all above it
BOTTOM = ("app.config", "app.jit")
# in the control code, what names the predictor or the human source (never probed)
PROBED_NAMES = ("predictor", "source", "human", "truth")
SIMULATOR = "app.cell.operator_sim"
# the modules that make decisions: none of them may know the simulated operator
DECIDERS = ("app.planning", "app.prediction", "app.safety", "app.control")
# the assembly of a trial's world, for the live and the headless runs (it may create a simulated operator)
WORLD = {"app.control.world"}


def _check(rule: str, offenders: dict[str, str]) -> None:
    """Fail on any module or kernel that breaks ``rule`` (``offenders``: name -> what it breaks)."""
    assert not offenders, f"{rule}:\n" + "\n".join(msg for _, msg in sorted(offenders.items()))


def _module_name(path: Path) -> str:
    rel = path.relative_to(APP.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


@cache
def _modules() -> dict[str, tuple[Path, ast.Module]]:
    out = {}
    for path in sorted(APP.rglob("*.py")):
        if "migrations" in path.parts:
            continue
        out[_module_name(path)] = (path, ast.parse(path.read_text(), filename=str(path)))
    return out


def _from_module(name: str, node: ast.ImportFrom) -> str:
    """The absolute name of the module of ``from ... import`` in module ``name`` (relative ones resolved)."""
    if not node.level:
        return node.module or ""
    package = name if _modules()[name][0].name == "__init__.py" else name.rpartition(".")[0]
    base = package.split(".")
    base = base[: len(base) - node.level + 1]
    return ".".join([*base, node.module] if node.module else base)


def _imports(name: str, tree: ast.Module) -> set[str]:
    """Every module that ``name`` imports, at module level or inside functions (``TYPE_CHECKING`` too)."""
    got: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            got.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            mod = _from_module(name, node)
            got.add(mod)
            # ``from app.planning import _kernels`` imports the submodule
            got.update(f"{mod}.{a.name}" for a in node.names if f"{mod}.{a.name}" in _modules())
    return got


def _app_imports(name: str) -> set[str]:
    mods = _modules()
    out = set()
    for mod in _imports(name, mods[name][1]):
        while mod and mod not in mods:
            mod = mod.rpartition(".")[0]
        if mod and mod != name and mod != "app":
            out.add(mod)
    return out


def _package(name: str) -> str:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_the_pure_core_imports_nothing_from_the_runtime_or_the_web() -> None:
    bad = []
    for name, (_, tree) in _modules().items():
        if _package(name) not in CORE:
            continue
        for mod in _imports(name, tree):
            top = mod.split(".")
            if top[0] == "app" and len(top) > 1 and top[1] in RUNTIME_AND_WEB:
                bad.append(f"{name} imports {mod}")
            if top[0] in WEB_DB_VIEW_LIBS:
                bad.append(f"{name} imports {mod}")
        # a lock that guards a shared cache is fine; starting threads is the runtime's job
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and node.attr in ("Thread", "Timer")) or (
                isinstance(node, ast.alias) and node.name in ("Thread", "Timer")
            ):
                bad.append(f"{name} uses threading.{getattr(node, 'attr', None) or node.name}")
    assert not bad, "\n".join(bad)


def test_the_cell_imports_nothing_from_the_runtime_the_studies_or_the_web() -> None:
    bad = [
        f"{name} imports {mod}"
        for name, (_, tree) in _modules().items()
        if _package(name) == "cell"
        for mod in _imports(name, tree)
        if mod.split(".")[:2]
        in (["app", p] for p in ("control", "study", "api", "ui", "bench", "commands", "cli"))
    ]
    assert not bad, "\n".join(bad)


def test_the_bottom_imports_nothing_from_the_cell_or_above() -> None:
    bad = [
        f"{name} imports {mod}"
        for name, (_, tree) in _modules().items()
        if name in BOTTOM or name.startswith(tuple(f"{b}." for b in BOTTOM))
        for mod in _imports(name, tree)
        if mod.split(".")[:2] in (["app", p] for p in ("cell", *ABOVE_THE_CELL))
    ]
    assert not bad, "\n".join(bad)


def _private(part: str) -> bool:
    return part.startswith("_") and not (part.startswith("__") and part.endswith("__"))


def test_no_module_imports_another_packages_private_parts() -> None:
    """``import app.x._mod``, ``from app.x._mod import ...``, ``from app.x import _mod`` or ``_name`` from a
    module of another top-level package are all refused; within a package they are its own business."""
    bad = []
    for name, (_, tree) in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                got = [(a.name, None) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                got = [(_from_module(name, node), a.name) for a in node.names]
            else:
                continue
            for mod, imported in got:
                parts = mod.split(".")
                if parts[0] != "app" or len(parts) < 2 or _package(mod) == _package(name):
                    continue
                if any(_private(p) for p in parts[1:]) or (imported is not None and _private(imported)):
                    what = mod if imported is None else f"{imported} from {mod}"
                    bad.append(f"{name} imports {what}")
    assert not bad, "\n".join(bad)


def test_the_control_code_never_probes_the_predictor_or_the_source() -> None:
    """No ``hasattr(x, ...)`` or ``getattr(x, ...)`` in ``app.control`` on an ``x`` that names the predictor
    or the human source: what they can do is part of their protocol."""
    bad = []
    for name, (path, tree) in _modules().items():
        if _package(name) != "control":
            continue
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Name)
                and node.func.id in ("hasattr", "getattr")
                and node.args
            ):
                target = ast.unparse(node.args[0])
                if any(word in target.lower() for word in PROBED_NAMES):
                    bad.append(f"{path.relative_to(APP.parent)}:{node.lineno}: {ast.unparse(node)}")
    assert not bad, "\n".join(bad)


def test_nothing_that_decides_imports_the_simulated_operator() -> None:
    bad = [
        f"{name} imports {SIMULATOR}"
        for name in _modules()
        if name.startswith(DECIDERS) and name not in WORLD and SIMULATOR in _app_imports(name)
    ]
    assert not bad, "\n".join(bad)


def test_no_import_circles() -> None:
    graph = {name: _app_imports(name) for name in _modules()}
    # a package's __init__ that re-exports its modules is not a circle with them
    for name in graph:
        graph[name] = {m for m in graph[name] if not name.startswith(m + ".")}
    circles: list[list[str]] = []
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(n: str) -> None:
        state[n] = 1
        stack.append(n)
        for m in sorted(graph[n]):
            if state.get(m) == 1:
                circles.append([*stack[stack.index(m) :], m])
            elif m not in state:
                visit(m)
        stack.pop()
        state[n] = 2

    for n in sorted(graph):
        if n not in state:
            visit(n)
    assert not circles, "\n".join(" -> ".join(c) for c in circles)


def _is_kernel(fn: ast.FunctionDef) -> bool:
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        # numba's decorators, and the packages' own wrappers of them (``_jit``)
        if name.endswith("jit") or name in ("vectorize", "guvectorize", "cfunc"):
            return True
    return False


def test_no_numba_kernel_takes_more_than_12_parameters() -> None:
    bad = {}
    for name, (_, tree) in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef) and _is_kernel(node):
                a = node.args
                n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs) + bool(a.vararg) + bool(a.kwarg)
                if n > MAX_KERNEL_PARAMS:
                    bad[f"{name}.{node.name}"] = f"{name}.{node.name}: {n} parameters"
    _check("kernel_params", bad)


def test_runtime_code_never_imports_a_reference_implementation() -> None:
    refs = {n for n in _modules() if n.rpartition(".")[2] == "reference"}
    bad = [
        f"{name} imports {mod}"
        for name in _modules()
        if _package(name) != "bench" and name not in refs
        for mod in _app_imports(name) & refs
    ]
    assert not bad, "\n".join(bad)


def test_no_reference_forks_in_production_classes() -> None:
    """Production code chooses no implementation by a ``compiled=`` flag and keeps no ``*_reference``."""
    bad = {}
    for name, (_, tree) in _modules().items():
        if name.rpartition(".")[2] == "reference":
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                key = f"{name}.{node.name}"
                args = node.args.args + node.args.kwonlyargs
                if any(a.arg == "compiled" for a in args):
                    bad[key] = f"{key} takes compiled="
                if node.name.endswith("_reference") or node.name.startswith("_reference"):
                    bad[key] = f"{key} is a reference implementation"
    _check("reference_forks", bad)


def test_no_module_is_longer_than_1200_lines() -> None:
    bad = {}
    for name, (path, _) in _modules().items():
        n = len(path.read_text().splitlines())
        if n > MAX_LINES:
            bad[name] = f"{path.relative_to(APP.parent)}: {n} lines (at most {MAX_LINES})"
    _check("module_lines", bad)


def test_the_architecture_notes_list_exactly_the_modules_that_exist() -> None:
    doc = (APP.parent / "docs" / "architecture.md").read_text()
    listed = set(re.findall(r"^\| `(app/[\w/]+\.py)` \|", doc, flags=re.MULTILINE))
    present = {p.relative_to(APP.parent).as_posix() for p in APP.rglob("*.py") if "migrations" not in p.parts}
    assert listed == present, (
        "docs/architecture.md is out of date (run scripts/module_map.py): "
        f"missing {sorted(present - listed)}, gone {sorted(listed - present)}"
    )


def test_the_dead_names_are_gone() -> None:
    """Names nothing called (issue: one pipeline, typed seams) stay deleted."""
    import app.control.supervisor as supervisor
    import app.control.trajectory_views as trajectory_views
    import app.prediction.evaluate as evaluate
    import app.prediction.train as train
    import app.study.repository as repository
    import app.study.runner as runner
    import app.study.schemas as schemas
    from app.cell.operator_sim import _Body
    from app.safety.ssm import SSMParams

    gone = [
        (evaluate, "baseline_fns"),
        (train, "default_config"),
        (SSMParams, "human_distance_m"),
        (trajectory_views, "PlanLike"),
        (supervisor.Supervisor, "recent_decide_s"),
        (repository, "metrics_from_read"),
        (schemas, "TrialFinish"),
        (runner, "jobs_by_participant"),
        (_Body, "shoulders"),
    ]
    assert [name for owner, name in gone if hasattr(owner, name)] == []
