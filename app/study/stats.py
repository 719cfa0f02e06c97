"""Analysis of a study: the paper's Table I per method, paired tests per metric, tables and box plots.

The unit of analysis is the participant: each participant's completed trials of one method are averaged
(usually there is exactly one), and the paired tests compare the two methods within participants.

Test choice per metric (paired differences d = proactive - reactive over the participants with both methods):

* fewer than 3 pairs, or every difference zero -> ``"not testable"`` (the reason says which);
* Shapiro-Wilk on d: p > 0.05 (normality not rejected) -> repeated-measures ANOVA (statsmodels ``AnovaRM``,
  one within factor: method), effect size partial eta squared (Cohen's d_z given too);
* otherwise (or when the differences are constant, so that normality cannot be judged) -> Wilcoxon
  signed-rank (zero differences dropped), effect size the matched-pairs rank-biserial correlation r.
"""

from __future__ import annotations

import csv
import io
import logging
import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from app.control.metrics import METHODS

log = logging.getLogger(__name__)

#: The paper's Table I.
TABLE_I_METRICS: tuple[str, ...] = (
    "completed_tasks",
    "avg_planning_time_s",
    "stop_replans_per_task",
    "online_replans_per_task",
)
#: Every metric of the report: Table I plus safety and efficiency.
REPORT_METRICS: tuple[str, ...] = (
    *TABLE_I_METRICS,
    "min_separation_m",
    "deadline_misses",
    "time_stopped_s",
    "mean_speed_scale",
    "stop_replans_moving",
    "violations",
    "violations_person_faster",
    "contacts",
    "harmful_contacts",
    "exceedance_s",
)
METRIC_LABELS: dict[str, str] = {
    "completed_tasks": "Completed tasks",
    "avg_planning_time_s": "Avg. planning time (s)",
    "stop_replans_per_task": "Avg. stop & replan (per task)",
    "online_replans_per_task": "Avg. online replan (per task)",
    "min_separation_m": "Min. separation (m)",
    "deadline_misses": "Deadline misses",
    "time_stopped_s": "Time stopped (s)",
    "mean_speed_scale": "Mean speed scale under way",
    "stop_replans_moving": "Stop & replans under way",
    "violations": "Violations (ground truth)",
    "violations_person_faster": "Violations, person faster than assumed",
    "contacts": "Contacts (ground truth)",
    "harmful_contacts": "Harmful contacts (ground truth)",
    "exceedance_s": "Person faster than assumed (s)",
}
#: The time budget's parts (:data:`app.control.supervisor_types.TIME_BUDGET`) as the trial rows store them,
#: and their names for people (the dashboard's).
BUDGET_LABELS: dict[str, str] = {
    "moving_full": "moving, full speed",
    "moving_scaled": "moving, slowed",
    "braking": "braking",
    "stopped": "held still",
    "planned_wait": "planned wait",
    "gripper": "gripper",
    "waiting_for_person": "waiting for the person",
    "waiting_for_plan": "waiting for a plan",
    "idle": "idle",
}
NORMALITY_ALPHA = 0.05
MIN_PAIRS = 3
NOT_TESTABLE = "not testable"


@dataclass(frozen=True)
class PairedTest:
    """Result of one paired comparison (proactive vs reactive) of one metric.

    Attributes:
        test: ``"wilcoxon"``, ``"anova_rm"`` or ``"not testable"``.
        why: Why that test (or why none).
        statistic: Wilcoxon W (the smaller signed-rank sum) or the ANOVA F; None when not testable.
        p_value: Two-sided p-value; None when not testable.
        effect_size: Rank-biserial r (Wilcoxon, in [-1, 1], > 0: proactive higher) or partial eta squared
            (ANOVA); None when not testable.
        effect_size_name: ``"rank_biserial_r"`` or ``"partial_eta_squared"``.
        cohens_dz: Mean difference / sd of the differences (None when the sd is zero or n < 3).
        n_pairs: Participants with a value for both methods.
        normality_p: Shapiro-Wilk p of the differences (None when not computed).
        mean_difference: Mean of proactive - reactive.
    """

    test: str
    why: str
    statistic: float | None = None
    p_value: float | None = None
    effect_size: float | None = None
    effect_size_name: str | None = None
    cohens_dz: float | None = None
    n_pairs: int = 0
    normality_p: float | None = None
    mean_difference: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {k: _finite_or_none(v) for k, v in asdict(self).items()}


def _finite_or_none(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _rank_biserial(d: np.ndarray) -> float:
    """Matched-pairs rank-biserial correlation of the non-zero differences ``d`` (n,)."""
    from scipy.stats import rankdata

    nz = d[d != 0]
    ranks = rankdata(np.abs(nz))
    w_pos = float(ranks[nz > 0].sum())
    w_neg = float(ranks[nz < 0].sum())
    return (w_pos - w_neg) / (w_pos + w_neg)


def paired_test(
    proactive: np.ndarray, reactive: np.ndarray, *, normality_alpha: float = NORMALITY_ALPHA
) -> PairedTest:
    """Compare two paired samples (one value per participant and method).

    Args:
        proactive: (n,) per-participant values under the proactive method.
        reactive: (n,) the same participants' values under the reactive method.
        normality_alpha: Shapiro-Wilk threshold: p above it -> repeated-measures ANOVA, else Wilcoxon.
    """
    from scipy import stats

    a = np.asarray(proactive, dtype=float)
    b = np.asarray(reactive, dtype=float)
    if a.shape != b.shape or a.ndim != 1:
        raise ValueError(f"paired samples must both be (n,), got {a.shape} and {b.shape}")
    d = a - b
    n = int(d.size)
    mean_d = float(d.mean()) if n else None
    if n < MIN_PAIRS:
        return PairedTest(
            NOT_TESTABLE,
            f"only {n} paired participants (a paired test needs >= {MIN_PAIRS})",
            n_pairs=n,
            mean_difference=mean_d,
        )
    if np.all(d == 0):
        return PairedTest(
            NOT_TESTABLE,
            "every paired difference is zero (the methods gave identical values)",
            n_pairs=n,
            mean_difference=0.0,
        )
    sd_d = float(d.std(ddof=1))
    dz = mean_d / sd_d if sd_d > 0 else None
    if np.ptp(d) == 0:
        normality_p = None
        why = (
            "the paired differences are all equal (no spread, normality cannot be judged): "
            "Wilcoxon signed-rank"
        )
        use_anova = False
    else:
        normality_p = float(stats.shapiro(d).pvalue)
        use_anova = normality_p > normality_alpha
        if use_anova:
            why = (
                f"Shapiro-Wilk on the paired differences p = {normality_p:.3g} > {normality_alpha}: "
                "normality not rejected, so repeated-measures ANOVA (within factor: method)"
            )
        else:
            why = (
                f"Shapiro-Wilk on the paired differences p = {normality_p:.3g} <= {normality_alpha}: "
                "not normal, so the Wilcoxon signed-rank test"
            )
    if use_anova:
        import pandas as pd
        from statsmodels.stats.anova import AnovaRM

        df = pd.DataFrame(
            {
                "participant": np.concatenate([np.arange(n), np.arange(n)]),
                "method": ["proactive"] * n + ["reactive"] * n,
                "value": np.concatenate([a, b]),
            }
        )
        table = AnovaRM(df, depvar="value", subject="participant", within=["method"]).fit().anova_table
        f_value = float(table["F Value"].iloc[0])
        df1, df2 = float(table["Num DF"].iloc[0]), float(table["Den DF"].iloc[0])
        p = float(table["Pr > F"].iloc[0])
        eta = f_value * df1 / (f_value * df1 + df2)
        return PairedTest("anova_rm", why, f_value, p, eta, "partial_eta_squared", dz, n, normality_p, mean_d)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # scipy warns about ties/zeros with small n
        res = stats.wilcoxon(a, b, zero_method="wilcox", alternative="two-sided")
    n_zero = int(np.sum(d == 0))
    if n_zero:
        why += f" ({n_zero} zero differences dropped)"
    return PairedTest(
        "wilcoxon",
        why,
        float(res.statistic),
        float(res.pvalue),
        _rank_biserial(d),
        "rank_biserial_r",
        dz,
        n,
        normality_p,
        mean_d,
    )


def _value(row: Mapping[str, Any], metric: str) -> float | None:
    v = row.get(metric)
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


def per_participant(rows: Sequence[Mapping[str, Any]], metric: str) -> dict[str, dict[str, float]]:
    """``{method: {participant_code: mean of that participant's values}}`` over rows with a finite value."""
    acc: dict[str, dict[str, list[float]]] = {m: {} for m in METHODS}
    for row in rows:
        v = _value(row, metric)
        if v is None or row["method"] not in acc:
            continue
        acc[row["method"]].setdefault(str(row["participant_code"]), []).append(v)
    return {m: {code: float(np.mean(vs)) for code, vs in by.items()} for m, by in acc.items()}


def summarize_rows(
    rows: Sequence[Mapping[str, Any]], *, metrics: Sequence[str] = REPORT_METRICS
) -> dict[str, Any]:
    """The report object from flat trial rows (:meth:`StudyRepository.metrics_rows`).

    Returns:
        ``{"proactive": {metric: {"mean", "sd", "n"}}, "reactive": {...}, "p_values": {metric: p | None},
        "tests": {metric: PairedTest.to_json()}, "n_participants": participants with both methods,
        "n_trials": {method: count}, "metrics": [...], "labels": {metric: its name for people}}``. Means
        and sds are over participants (sd with ddof=1; None when n < 2); every number is finite or None.
    """
    out: dict[str, Any] = {m: {} for m in METHODS}
    out["p_values"] = {}
    out["tests"] = {}
    for metric in metrics:
        by = per_participant(rows, metric)
        for m in METHODS:
            vals = np.array(list(by[m].values()), dtype=float)
            out[m][metric] = {
                "mean": _finite_or_none(vals.mean()) if vals.size else None,
                "sd": _finite_or_none(vals.std(ddof=1)) if vals.size >= 2 else None,
                "n": int(vals.size),
            }
        codes = sorted(set(by["proactive"]) & set(by["reactive"]))
        test = paired_test(
            np.array([by["proactive"][c] for c in codes], dtype=float),
            np.array([by["reactive"][c] for c in codes], dtype=float),
        )
        out["tests"][metric] = test.to_json()
        out["p_values"][metric] = _finite_or_none(test.p_value)
    paired = {str(r["participant_code"]) for r in rows if r["method"] == "proactive"} & {
        str(r["participant_code"]) for r in rows if r["method"] == "reactive"
    }
    out["n_participants"] = len(paired)
    out["n_trials"] = {m: sum(1 for r in rows if r["method"] == m) for m in METHODS}
    out["metrics"] = list(metrics)
    out["labels"] = {m: METRIC_LABELS.get(m, m) for m in metrics}
    out["time_budget_s"] = {m: _time_budget([r for r in rows if r["method"] == m]) for m in METHODS}
    out["arrival_error_s"] = {m: _arrival_error([r for r in rows if r["method"] == m]) for m in METHODS}
    return out


def _time_budget(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Where the trials' time went: per :data:`BUDGET_LABELS` part the mean seconds per trial, over the trials
    that kept a whole budget (``trials``; those stored before it was recorded, or before the wait for the
    person was counted apart from the wait for a plan (revision 0006), have none: their parts would not add
    up)."""
    cols = [f"budget_{k}_s" for k in BUDGET_LABELS]
    kept = [r for r in rows if all(r.get(c) is not None for c in cols)]
    out: dict[str, Any] = {"trials": len(kept)}
    for k, c in zip(BUDGET_LABELS, cols, strict=True):
        out[k] = _finite_or_none(float(np.mean([float(r[c]) for r in kept]))) if kept else None
    return out


def _arrival_error(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The plans' predicted against executed arrivals, over the trials with arrivals (``trials``): the median
    over the trials of each trial's median absolute error, the mean of their biases (executed minus
    predicted; positive: late), the median of their median plan durations, and ``relative``, the first over
    the third (the issue's measure: at most 0.15 means the plans say when the robot arrives)."""
    have = [r for r in rows if (r.get("arrivals") or 0) > 0 and r.get("median_plan_s") is not None]
    if not have:
        return {"trials": 0, "median_abs": None, "bias": None, "median_plan_s": None, "relative": None}
    med = float(np.median([float(r["arrival_error_median_abs_s"]) for r in have]))
    plan = float(np.median([float(r["median_plan_s"]) for r in have]))
    return {
        "trials": len(have),
        "median_abs": _finite_or_none(med),
        "bias": _finite_or_none(float(np.mean([float(r["arrival_error_bias_s"]) for r in have]))),
        "median_plan_s": _finite_or_none(plan),
        "relative": _finite_or_none(med / plan) if plan > 0 else None,
    }


def summarize(
    source: Any,
    *,
    session_id: int | None = None,
    metrics: Sequence[str] = REPORT_METRICS,
) -> dict[str, Any]:
    """The ``hrc report --json`` object over the completed trials of ``source`` (a
    :class:`~app.study.repository.StudyRepository`, or a sequence of rows as from its ``metrics_rows``),
    optionally restricted to one study session. See :func:`summarize_rows` for the shape."""
    if hasattr(source, "metrics_rows"):
        rows = source.metrics_rows(session_id=session_id, status="completed")
    else:
        rows = [r for r in source if r.get("status", "completed") == "completed"]
        if session_id is not None:
            rows = [r for r in rows if r.get("session_id") == session_id]
    out = summarize_rows(rows, metrics=metrics)
    out["session_id"] = session_id
    return out


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, int):
        return str(v)
    return f"{v:.{digits}g}" if abs(v) < 1e-3 and v != 0 else f"{v:.{digits}f}"


def markdown_table(summary: Mapping[str, Any]) -> str:
    """Table I (mean ± sd per method) and the paired tests, as Markdown."""
    metrics = summary["metrics"]
    head = "| Method | " + " | ".join(METRIC_LABELS.get(m, m) for m in metrics) + " |"
    lines = [head, "|" + "---|" * (len(metrics) + 1)]
    for method in METHODS:
        cells = [f"{_fmt(summary[method][m]['mean'])} ± {_fmt(summary[method][m]['sd'])}" for m in metrics]
        lines.append(f"| {method} | " + " | ".join(cells) + " |")
    lines += ["", f"Paired participants: {summary['n_participants']}", ""]
    lines += ["| Metric | Test | Statistic | p | Effect size | Why |", "|---|---|---|---|---|---|"]
    for m in metrics:
        t = summary["tests"][m]
        effect = "–" if t["effect_size"] is None else f"{t['effect_size_name']} = {_fmt(t['effect_size'])}"
        p = "–" if t["p_value"] is None else f"{t['p_value']:.3g}"
        label = METRIC_LABELS.get(m, m)
        lines.append(f"| {label} | {t['test']} | {_fmt(t['statistic'])} | {p} | {effect} | {t['why']} |")
    budget = summary.get("time_budget_s")
    if budget is not None:
        lines += ["", "Where the time went (mean s per trial):", ""]
        lines += ["| Method | " + " | ".join(BUDGET_LABELS.values()) + " | trials |"]
        lines += ["|" + "---|" * (len(BUDGET_LABELS) + 2)]
        for method in METHODS:
            b = budget[method]
            cells = [_fmt(b[k], 1) for k in BUDGET_LABELS]
            lines.append(f"| {method} | " + " | ".join(cells) + f" | {b['trials']} |")
    arrivals = summary.get("arrival_error_s")
    if arrivals is not None:
        lines += ["", "Predicted against executed arrival (median over trials):", ""]
        lines += ["| Method | median abs. error (s) | bias (s) | median plan (s) | relative | trials |"]
        lines += ["|---|---|---|---|---|---|"]
        for method in METHODS:
            a = arrivals[method]
            lines.append(
                f"| {method} | {_fmt(a['median_abs'])} | {_fmt(a['bias'])} | {_fmt(a['median_plan_s'])} | "
                f"{_fmt(a['relative'])} | {a['trials']} |"
            )
    return "\n".join(lines) + "\n"


CSV_COLUMNS: tuple[str, ...] = (
    "metric",
    "proactive_mean",
    "proactive_sd",
    "proactive_n",
    "reactive_mean",
    "reactive_sd",
    "reactive_n",
    "test",
    "statistic",
    "p_value",
    "effect_size",
    "effect_size_name",
    "cohens_dz",
    "n_pairs",
    "normality_p",
    "why",
)


def csv_table(summary: Mapping[str, Any]) -> str:
    """One CSV row per metric: both methods' mean, sd, n and the paired test (empty cells for None)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for m in summary["metrics"]:
        t = summary["tests"][m]
        row = [m]
        for method in METHODS:
            s = summary[method][m]
            row += [s["mean"], s["sd"], s["n"]]
        row += [
            t[k]
            for k in (
                "test",
                "statistic",
                "p_value",
                "effect_size",
                "effect_size_name",
                "cohens_dz",
                "n_pairs",
                "normality_p",
                "why",
            )
        ]
        w.writerow(["" if v is None else (repr(v) if isinstance(v, float) else v) for v in row])
    return buf.getvalue()


def box_plots(
    rows: Sequence[Mapping[str, Any]],
    path: Path,
    *,
    metrics: Sequence[str] = REPORT_METRICS,
    summary: Mapping[str, Any] | None = None,
) -> Path:
    """Box plots (one panel per metric) of the per-participant values of both methods, as a PNG.

    Paired participants are joined by thin lines; each panel's title gives the test's p-value when
    ``summary`` is passed. Drawn on matplotlib's Agg canvas (no display, pyplot untouched).
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    ncols = 4
    nrows = max(1, math.ceil(len(metrics) / ncols))
    fig = Figure(figsize=(4.0 * ncols, 3.6 * nrows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, squeeze=False).ravel()
    for ax, metric in zip(axes, metrics, strict=False):
        by = per_participant(rows, metric)
        data = [list(by[m].values()) for m in METHODS]
        ax.boxplot(data, tick_labels=list(METHODS), widths=0.5, showmeans=True)
        for code in sorted(set(by["proactive"]) & set(by["reactive"])):
            ax.plot([1, 2], [by["proactive"][code], by["reactive"][code]], color="0.6", lw=0.6, marker=".")
        title = METRIC_LABELS.get(metric, metric)
        if summary is not None and metric in summary["tests"]:
            p = summary["p_values"].get(metric)
            test = summary["tests"][metric]["test"]
            title += f"\n{test}" if p is None else f"\n{test} p = {p:.3g}"
        ax.set_title(title, fontsize=9)
        ax.grid(axis="y", alpha=0.3)
    for ax in axes[len(metrics) :]:
        ax.set_visible(False)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def write_report(
    rows: Sequence[Mapping[str, Any]],
    out_dir: Path,
    *,
    summary: Mapping[str, Any] | None = None,
    metrics: Sequence[str] = REPORT_METRICS,
) -> dict[str, Path]:
    """Write ``table.md``, ``table.csv``, ``summary.json`` and ``boxplots.png`` into ``out_dir``."""
    import json

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = summary if summary is not None else summarize_rows(rows, metrics=metrics)
    paths = {
        "markdown": out_dir / "table.md",
        "csv": out_dir / "table.csv",
        "json": out_dir / "summary.json",
        "boxplots": out_dir / "boxplots.png",
    }
    paths["markdown"].write_text(markdown_table(summary), encoding="utf-8")
    paths["csv"].write_text(csv_table(summary), encoding="utf-8")
    paths["json"].write_text(json.dumps(summary, indent=2, allow_nan=False), encoding="utf-8")
    box_plots(rows, paths["boxplots"], metrics=metrics, summary=summary)
    log.info("study report written to %s", out_dir)
    return paths
