"""The simulated population: how each simulated participant's body and behaviour are drawn.

A :class:`Population` maps every parameter of a simulated participant
(:class:`~app.cell.operator_sim.OperatorParams`, which loads it) to a distribution
read from a TOML file (the shipped default is ``app/assets/population.toml``, which documents the format
and the sources). Drawing is reproducible: the same population and seed give the same participant, and
the shipped file gives exactly the participants the project drew before the population became a file.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["DEFAULT_POPULATION_PATH", "Population", "PopulationError", "load_population"]

DEFAULT_POPULATION_PATH = Path(__file__).resolve().parents[1] / "assets" / "population.toml"

#: distribution name -> (required keys, optional keys)
_KINDS: dict[str, tuple[tuple[str, ...], tuple[str, ...]]] = {
    "normal": (("mean", "sd"), ("lo", "hi")),
    "lognormal": (("median", "sigma"), ("lo", "hi")),
    "uniform": (("lo", "hi"), ()),
    "beta": (("a", "b"), ()),
    "choice": (("values", "p"), ()),
}


class PopulationError(ValueError):
    """A population file that cannot be used; the message names the file, the entry and the reason."""


@dataclass(frozen=True, slots=True)
class _Dist:
    kind: str
    args: dict[str, Any]

    def draw(self, rng: np.random.Generator) -> Any:
        a = self.args
        if self.kind == "normal":
            x = rng.normal(a["mean"], a["sd"])
        elif self.kind == "lognormal":
            x = rng.lognormal(math.log(a["median"]), a["sigma"])
        elif self.kind == "uniform":
            return float(rng.uniform(a["lo"], a["hi"]))
        elif self.kind == "beta":
            return float(rng.beta(a["a"], a["b"]))
        else:  # choice
            return a["values"][0] if rng.random() < a["p"] else a["values"][1]
        if "lo" in a or "hi" in a:
            x = np.clip(x, a.get("lo", -math.inf), a.get("hi", math.inf))
        return float(x)


@dataclass(frozen=True)
class Population:
    """Distributions of the participants' parameters, in the order they are drawn.

    Attributes:
        name: Where it came from (a file path or ``"default"``).
        dists: ``(parameter, distribution)`` pairs in drawing order.
    """

    name: str
    dists: tuple[tuple[str, _Dist], ...]

    def draw(self, seed: int) -> dict[str, Any]:
        """One participant's parameters (a dict for ``OperatorParams(**...)``), reproducible from ``seed``."""
        rng = np.random.default_rng([int(seed), 0x0BE7A])
        return {name: dist.draw(rng) for name, dist in self.dists}

    def to_dict(self) -> dict[str, dict[str, dict[str, Any]]]:
        """The population as the TOML document it was read from."""
        return {name: {d.kind: dict(d.args)} for name, d in self.dists}


def load_population(
    path: str | Path | None, parameters: Sequence[str], check: Callable[[dict[str, Any]], object]
) -> Population:
    """Read a population file (``None``: the shipped one).

    Args:
        path: The TOML file.
        parameters: The names every file must give, once each.
        check: Called with a few drawn participants; raises ``ValueError`` for an invalid one.

    Raises:
        PopulationError: The file is missing or not TOML, a parameter is unknown or missing, a
            distribution is unknown or has wrong arguments, or it draws invalid participants.
    """
    p = DEFAULT_POPULATION_PATH if path is None else Path(path)
    if not p.is_file():
        raise PopulationError(f"population file {p} does not exist")
    try:
        doc = tomllib.loads(p.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise PopulationError(f"population file {p} is not valid TOML: {exc}") from exc
    wanted = list(parameters)
    unknown = sorted(set(doc) - set(wanted))
    missing = [n for n in wanted if n not in doc]
    if unknown or missing:
        raise PopulationError(
            f"population file {p}: unknown parameter(s) {unknown}, missing {missing}; "
            f"the parameters are {wanted}"
        )
    dists = []
    for name, entry in doc.items():
        if not isinstance(entry, dict) or len(entry) != 1:
            raise PopulationError(f"population file {p}: [{name}] must hold one distribution, e.g. uniform")
        ((kind, args),) = entry.items()
        if kind not in _KINDS or not isinstance(args, dict):
            raise PopulationError(f"population file {p}: [{name}] {kind!r} is not one of {sorted(_KINDS)}")
        need, optional = _KINDS[kind]
        bad = sorted(set(args) - set(need) - set(optional))
        lack = [k for k in need if k not in args]
        if bad or lack:
            raise PopulationError(
                f"population file {p}: [{name}] {kind} takes {list(need)} (optional {list(optional)}); "
                f"unknown {bad}, missing {lack}"
            )
        if kind == "choice":
            values = args["values"]
            if not (isinstance(values, list) and len(values) == 2 and 0.0 <= float(args["p"]) <= 1.0):
                raise PopulationError(
                    f"population file {p}: [{name}] choice needs two values and p in [0, 1]"
                )
        elif not all(isinstance(v, int | float) and math.isfinite(v) for v in args.values()):
            raise PopulationError(f"population file {p}: [{name}] {kind} arguments must be finite numbers")
        dists.append((name, _Dist(kind, dict(args))))
    pop = Population(name="default" if path is None else str(p), dists=tuple(dists))
    try:  # every draw must make a valid participant: check a few
        for seed in range(8):
            check(pop.draw(seed))
    except ValueError as exc:
        raise PopulationError(f"population file {p} draws an invalid participant: {exc}") from exc
    return pop
