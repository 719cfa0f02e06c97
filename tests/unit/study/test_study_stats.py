"""Paired tests (known answers against scipy), degenerate cases, the report object and files."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from app.study.stats import (
    BUDGET_LABELS,
    REPORT_METRICS,
    TABLE_I_METRICS,
    csv_table,
    markdown_table,
    paired_test,
    summarize,
    write_report,
)


def test_normal_differences_use_repeated_measures_anova_equal_to_the_paired_t_test() -> None:
    rng = np.random.default_rng(1)
    reactive = rng.normal(12.0, 2.0, size=10)
    proactive = reactive + rng.normal(2.5, 1.0, size=10)
    assert stats.shapiro(proactive - reactive).pvalue > 0.05  # the premise of this case
    r = paired_test(proactive, reactive)
    t = stats.ttest_rel(proactive, reactive)
    assert r.test == "anova_rm" and "Shapiro-Wilk" in r.why and r.normality_p > 0.05
    assert r.statistic == pytest.approx(t.statistic**2, rel=1e-9)  # F(1, n-1) = t^2
    assert r.p_value == pytest.approx(t.pvalue, rel=1e-9)
    assert r.effect_size_name == "partial_eta_squared"
    assert r.effect_size == pytest.approx(t.statistic**2 / (t.statistic**2 + 9), rel=1e-9)
    d = proactive - reactive
    assert r.cohens_dz == pytest.approx(d.mean() / d.std(ddof=1))
    assert r.n_pairs == 10


def test_skewed_differences_use_wilcoxon_with_rank_biserial_r() -> None:
    reactive = np.zeros(10)
    proactive = np.array([0.1, 0.2, 0.15, 0.3, 5.0, 8.0, 12.0, 0.25, -0.05, 20.0])
    r = paired_test(proactive, reactive)
    assert stats.shapiro(proactive).pvalue <= 0.05
    w = stats.wilcoxon(proactive, reactive)
    assert r.test == "wilcoxon" and "not normal" in r.why
    assert r.statistic == w.statistic and r.p_value == pytest.approx(w.pvalue)
    # ranks of |d|: -0.05 has rank 1, the other nine are positive: r = (54 - 1) / 55
    assert r.effect_size_name == "rank_biserial_r" and r.effect_size == pytest.approx(53 / 55)


def test_rank_biserial_of_a_hand_example() -> None:
    # |d| ranks 1..4 with the largest negative: W+ = 6, W- = 4 -> r = 0.2 (zero dropped); constant spread
    # is not the case here, so force Wilcoxon with an impossible normality threshold.
    r = paired_test(np.array([1.0, 2.0, 3.0, -4.0, 0.0]), np.zeros(5), normality_alpha=1.0)
    assert r.test == "wilcoxon" and "1 zero differences dropped" in r.why
    assert r.effect_size == pytest.approx(0.2)


@pytest.mark.parametrize(
    ("a", "b", "why"),
    [
        ([1.0, 2.0], [0.0, 1.0], "only 2 paired participants"),
        ([], [], "only 0 paired participants"),
        ([3.0, 4.0, 5.0, 6.0], [3.0, 4.0, 5.0, 6.0], "every paired difference is zero"),
    ],
)
def test_degenerate_cases_are_not_testable(a: list[float], b: list[float], why: str) -> None:
    r = paired_test(np.array(a), np.array(b))
    assert r.test == "not testable" and why in r.why
    assert r.p_value is None and r.statistic is None and r.effect_size is None
    json.dumps(r.to_json(), allow_nan=False)


def test_constant_nonzero_differences_fall_back_to_wilcoxon() -> None:
    r = paired_test(np.array([2.0, 3.0, 4.0, 5.0]), np.array([1.0, 2.0, 3.0, 4.0]))
    assert r.test == "wilcoxon" and "no spread" in r.why and r.normality_p is None
    assert r.p_value is not None and 0 < r.p_value <= 1 and r.effect_size == 1.0


def _rows() -> list[dict[str, Any]]:
    rng = np.random.default_rng(7)
    rows = []
    for i in range(8):
        base = rng.normal(12, 2)
        for method in ("proactive", "reactive"):
            rows.append(
                {
                    "participant_code": f"P{i}",
                    "method": method,
                    "status": "completed",
                    "completed_tasks": int(base + (3 if method == "proactive" else 0) + rng.integers(0, 2)),
                    "avg_planning_time_s": float(rng.normal(0.2, 0.02)),
                    "stop_replans_per_task": float(rng.exponential(0.3 if method == "proactive" else 0.6)),
                    "online_replans_per_task": float(rng.exponential(2.0 if method == "proactive" else 0.5)),
                    "min_separation_m": None if i == 0 else float(rng.normal(0.4, 0.05)),
                    "deadline_misses": 0,
                    "time_stopped_s": float(rng.normal(10, 2)),
                }
            )
    # one participant with only one method: in the descriptive n, not in the pairs
    rows.append({**rows[0], "participant_code": "solo", "method": "reactive", "completed_tasks": 9})
    return rows


def test_summary_object_has_the_report_shape() -> None:
    s = summarize(_rows())
    json.dumps(s, allow_nan=False)
    assert s["n_participants"] == 8
    # every metric has a name for people (the operator page shows them)
    assert list(s["labels"]) == list(REPORT_METRICS) and s["labels"]["completed_tasks"] == "Completed tasks"
    for method in ("proactive", "reactive"):
        assert set(s[method]) == set(REPORT_METRICS)
        for m in TABLE_I_METRICS:
            assert set(s[method][m]) >= {"mean", "sd"}
    assert s["reactive"]["completed_tasks"]["n"] == 9 and s["proactive"]["completed_tasks"]["n"] == 8
    assert s["tests"]["min_separation_m"]["n_pairs"] == 7  # the None (no person seen) is left out
    assert (
        s["tests"]["deadline_misses"]["test"] == "not testable" and s["p_values"]["deadline_misses"] is None
    )
    assert s["tests"]["completed_tasks"]["test"] in ("wilcoxon", "anova_rm")
    assert s["p_values"]["completed_tasks"] < 0.01
    for m in REPORT_METRICS:
        assert set(s["tests"][m]) >= {"test", "why", "statistic", "effect_size"}
    solo = np.mean([r["completed_tasks"] for r in _rows() if r["method"] == "reactive"])
    assert s["reactive"]["completed_tasks"]["mean"] == pytest.approx(solo)


def test_aborted_trials_are_left_out() -> None:
    rows = _rows()
    rows.append({**rows[0], "status": "aborted", "completed_tasks": 1000})
    assert (
        summarize(rows)["proactive"]["completed_tasks"] == summarize(_rows())["proactive"]["completed_tasks"]
    )


def test_report_files(tmp_path: Path) -> None:
    rows = _rows()
    s = summarize(rows)
    paths = write_report(rows, tmp_path / "rep", summary=s)
    assert paths["boxplots"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert json.loads(paths["json"].read_text()) == json.loads(json.dumps(s))
    md = paths["markdown"].read_text()
    assert md == markdown_table(s) and "| proactive |" in md and "not testable" in md
    df = pd.read_csv(paths["csv"])
    assert list(df["metric"]) == list(REPORT_METRICS)
    assert df.loc[df["metric"] == "completed_tasks", "proactive_mean"].item() == pytest.approx(
        s["proactive"]["completed_tasks"]["mean"]
    )
    assert paths["csv"].read_text() == csv_table(s)


def test_the_report_says_where_the_time_went_and_whether_the_plans_said_when_the_robot_arrives() -> None:
    from app.control.supervisor_types import TIME_BUDGET

    rows = _rows()
    parts = list(BUDGET_LABELS)
    assert tuple(parts) == TIME_BUDGET
    for i, r in enumerate(rows):
        r.update({f"budget_{k}_s": float(i + j) for j, k in enumerate(parts)})
        r.update(arrivals=3, arrival_error_median_abs_s=0.1 * i, arrival_error_bias_s=0.05, median_plan_s=2.0)
    # a trial stored before the budget was kept (NULL columns), one without arrivals: left out, not zeros
    rows[0].update({f"budget_{k}_s": None for k in parts})
    rows[2].update(arrivals=0, arrival_error_median_abs_s=None, arrival_error_bias_s=None)
    s = summarize(rows)
    json.dumps(s, allow_nan=False)
    pro = [i for i, r in enumerate(rows) if r["method"] == "proactive"]
    kept = [i for i in pro if i != 0]
    budget = s["time_budget_s"]["proactive"]
    assert budget["trials"] == len(kept) == 7
    for j, k in enumerate(parts):
        assert budget[k] == pytest.approx(np.mean([i + j for i in kept]))
    arrivals = s["arrival_error_s"]["proactive"]
    with_arrivals = [i for i in pro if i != 2]
    assert arrivals["trials"] == 7
    assert arrivals["median_abs"] == pytest.approx(np.median([0.1 * i for i in with_arrivals]))
    assert arrivals["bias"] == pytest.approx(0.05) and arrivals["median_plan_s"] == 2.0
    assert arrivals["relative"] == pytest.approx(arrivals["median_abs"] / 2.0)
    md = markdown_table(s)
    assert "Where the time went" in md and "waiting for a plan" in md and "Predicted against executed" in md
    # rows without any of it (an old database): the report says so instead of inventing zeros
    bare = summarize(_rows())
    assert bare["time_budget_s"]["reactive"] == {"trials": 0, **dict.fromkeys(parts)}
    assert bare["arrival_error_s"]["reactive"]["trials"] == 0
