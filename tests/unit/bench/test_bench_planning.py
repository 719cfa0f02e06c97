"""``hrc bench planning``: the statistics are over successful runs, ratios are per query, the solvable set is
what some search proved solvable; and a quick run prints every key. No assertion on any time."""

from __future__ import annotations

import pytest

from app.bench import planning as bp
from app.bench.planning import Run
from app.config import Settings
from app.control.engine import EngineOptions
from app.safety.stopping import UR5E_STOP


def _runs(walls: list[float], oks: list[bool], reasons: list[str] | None = None) -> list[Run]:
    reasons = reasons or ["ok" if ok else "deadline" for ok in oks]
    return [Run(w, w / 2, ok, r, 10) for w, ok, r in zip(walls, oks, reasons, strict=True)]


def test_percentiles_and_empty() -> None:
    assert bp.percentiles([]) == {"p50": None, "p95": None, "n": 0}
    got = bp.percentiles([0.001, 0.002, 0.003], scale=1e3)
    assert got == {"p50": 2.0, "p95": pytest.approx(2.9), "n": 3}


def test_successful_ms_leaves_failures_out() -> None:
    runs = _runs([0.001, 0.002, 5.0, 0.003], [True, True, False, True])
    got = bp.successful_ms(runs)
    assert got["n"] == 3 and got["p50"] == 2.0 and got["p95"] < 3.0  # the 5-s failure is not in it
    assert bp.successful_ms(runs, cpu=True)["p50"] == 1.0


def test_ratios_are_per_query_over_queries_where_both_succeeded() -> None:
    num = _runs([0.010, 0.030, 0.020, 0.040], [True, True, False, True])
    den = _runs([0.005, 0.010, 0.001, 0.040], [True, True, True, False])
    # query 0: 2.0, query 1: 3.0; query 2 (time-variant failed) and 3 (static failed) are left out
    assert bp.per_query_ratios(num, den) == pytest.approx([2.0, 3.0])
    # not a ratio of medians (that would be 0.025 / 0.0075 = 3.33)
    assert bp.percentiles(bp.per_query_ratios(num, den), digits=2)["p50"] == 2.5
    with pytest.raises(ValueError, match="per query"):
        bp.per_query_ratios(num, den[:3])


def test_reason_key_and_failure_counts() -> None:
    assert bp.reason_key("goal blocked by the person from t=+0.40 s on") == "goal blocked by the person"
    assert (
        bp.reason_key("goal unreachable: every way into it is blocked (3 expansions)") == "goal unreachable"
    )
    assert bp.reason_key("goal unreachable: no safe path found after 12 expansions") == "goal unreachable"
    assert bp.reason_key("deadline") == "deadline"
    runs = _runs(
        [0.1] * 5,
        [True, False, False, False, True],
        ["ok", "deadline", "goal blocked by the person from t=+1.00 s on", "deadline", "ok"],
    )
    assert bp.failure_counts(runs) == {"deadline": 2, "goal blocked by the person": 1}


def test_solvable_set_is_the_union_of_verified_plans_and_the_generous_verdict() -> None:
    seq = [True, False, False, False, False]
    par = [False, True, False, False, False]
    generous = [True, True, True, False, None]  # 3: proved unsolvable; 4: out of its budget
    got = bp.solvability([seq, par], generous)
    assert got == [True, True, True, False, None]
    # a timed search's plan proves solvability even if the generous verdict said otherwise
    assert bp.solvability([[True]], [False]) == [True]
    par_runs = _runs([0.01] * 5, par)
    # solvable: queries 0, 1, 2; the parallel search solved 1 of them
    assert bp.solvable_success(par_runs, got) == pytest.approx(1 / 3, abs=1e-4)
    assert bp.solvable_success(par_runs, [False] * 5) is None


def test_summarise_shape_and_like_for_like() -> None:
    n = 4
    runs = {
        "plan": _runs([0.020, 0.040, 0.9, 0.030], [True, True, False, True]),
        "parallel_plan": _runs([0.010, 0.020, 1.0, 0.012], [True, True, False, False]),
        "static": _runs([0.010, 0.010, 0.005, 0.010], [True] * n),
        "parallel_static": _runs([0.005, 0.010, 0.005, 0.006], [True] * n),
        "emergency": _runs([0.0003] * n, [True, True, True, False], ["stay", "ok", "ok", "no plan"]),
    }
    out = bp.summarise(runs, [True, True, False, True])
    for c in bp.CONFIGS:
        assert set(out[f"{c}_ms"]) == {"p50", "p95", "n"}
        assert set(out["cpu_ms"][c]) == {"p50", "p95", "n"}
    assert out["plan_ms"]["n"] == 3 and out["parallel_plan_ms"]["n"] == 2 and out["emergency_ms"]["n"] == 3
    tv = out["time_variant_over_static"]
    assert set(tv) == {"sequential", "parallel"}
    assert tv["sequential"]["n"] == 3 and tv["sequential"]["p50"] == 3.0  # ratios 2, 4, 3
    assert tv["parallel"]["n"] == 2 and tv["parallel"]["p50"] == 2.0  # ratios 2, 2
    assert out["success_rate"] == 0.5 and out["sequential_success_rate"] == 0.75
    assert out["emergency_success_rate"] == 0.75
    assert (out["solvable"], out["unsolvable"], out["undecided"]) == (3, 1, 0)
    assert out["success_rate_solvable"] == pytest.approx(2 / 3, abs=1e-4)
    assert out["sequential_success_rate_solvable"] == 1.0
    assert out["failures"]["plan"] == {"deadline": 1}
    assert out["failures"]["parallel_plan"] == {"deadline": 2}
    assert out["failures"]["emergency"] == {"no plan": 1}
    assert out["failures"]["static"] == {}
    with pytest.raises(ValueError, match="one run per query"):
        bp.summarise(runs, [True] * (n + 1))


def test_phases_are_over_the_successful_runs_with_their_share_of_the_wall_time() -> None:
    runs = [
        Run(0.010, 0.005, True, phases_s=(0.006, 0.001, 0.003)),
        Run(0.030, 0.015, True, phases_s=(0.020, 0.002, 0.008)),
        Run(0.900, 0.450, False, "deadline", phases_s=(0.900, 0.0, 0.0)),  # a failure: left out
        Run(0.0003, 0.0003, True),  # no phases reported (an emergency plan): left out
    ]
    out = bp.phases_ms(runs)
    assert out["search"] == {"p50": 13.0, "p95": 19.3, "n": 2}
    assert out["shortcut"]["n"] == 2 and out["finish"]["p50"] == 5.5
    assert out["share"] == {"search": 0.65, "shortcut": 0.075, "finish": 0.275}
    empty = bp.phases_ms([Run(0.1, 0.1, False, "deadline")])
    assert empty["search"] == {"p50": None, "p95": None, "n": 0} and empty["share"]["finish"] is None


@pytest.mark.slow
def test_quick_run_prints_every_key() -> None:
    out = bp.run(quick=True, progress=False)
    for key in ("plan_ms", "parallel_plan_ms", "static_ms", "parallel_static_ms", "emergency_ms"):
        assert set(out[key]) == {"p50", "p95", "n"}
    assert set(out["time_variant_over_static"]) == {"sequential", "parallel"}
    for c in ("plan", "parallel_plan", "static", "parallel_static"):
        phases = out["phases_ms"][c]
        assert set(phases) == {"search", "shortcut", "finish", "share"}
        assert phases["search"]["n"] == out[f"{c}_ms"]["n"]
        assert 0.0 < sum(phases["share"].values()) <= 1.0 + 1e-9
    assert out["solvable"] + out["unsolvable"] + out["undecided"] == out["queries"]
    assert set(out["failures"]) == set(bp.CONFIGS)
    assert out["violations"] == 0
    assert "one thread" in out["parallel_kind"]
    # the clearance it planned and checked with: the runtime's T_r and the cell's stopping model
    assert out["clearance"]["t_reaction_s"] == pytest.approx(
        Settings().reaction_time_s(EngineOptions().servo_period_s)
    )
    assert out["clearance"]["stopping"] == {
        "decel_mps2": UR5E_STOP.decel_mps2,
        "joint_decel_radps2": list(UR5E_STOP.joint_decel_radps2),
        "delay_s": UR5E_STOP.delay_s,
    }
    assert out["threads"]["queries"] == 12 and out["threads"]["threads"] >= 2
    assert 0.0 <= out["success_rate"] <= 1.0
