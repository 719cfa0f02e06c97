"""Models, engine settings and migrations of the study database (SQLite)."""

from __future__ import annotations

from datetime import datetime
from pathlib import Path

import pytest
from alembic import command
from sqlalchemy import inspect, text

from app.control.metrics import TrialMetrics
from app.study.db import DatabaseError, alembic_config, current_revision, make_engine, upgrade_to_head
from app.study.models import METRIC_COLUMNS, Base, TrialMetricsRow, UTCDateTime

HEAD = "0009"
#: The ground-truth monitor's columns (revision 0004).
_SAFETY_0004 = ("contacts", "violation_time_s", "violations_iso", "intrusions", "min_separation_moving_m")
#: The time budget's wait for the person and the stops of a moving robot, counted apart (revision 0006).
_PERSON_0006 = ("budget_waiting_for_person_s", "stop_replans_moving")
_PFL_0007 = (
    "violations_person_faster",
    "harmful_contacts",
    "violations_measured_vh",
    "exceedance_s",
    "max_approach_mps",
)
#: The reactive method's plan as a candidate (revision 0008).
_CHOICES_0008 = ("plans_forecast", "plans_reactive", "plans_reactive_only", "reactive_gain_s")
#: The time budget's and the arrivals' columns (revision 0005).
_BUDGET_0005 = tuple(
    c for c in METRIC_COLUMNS if c.startswith(("budget_", "arrival", "median_plan")) and c not in _PERSON_0006
)


def test_one_metrics_column_per_trial_metrics_field() -> None:
    # A new TrialMetrics field needs a column and a migration: this test names it.
    assert set(METRIC_COLUMNS) == set(TrialMetrics.field_names()) - {"method"}
    columns = {c.name for c in TrialMetricsRow.__table__.columns}
    assert columns == {"trial_id", *METRIC_COLUMNS}


def test_utc_datetime_rejects_naive_values() -> None:
    with pytest.raises(ValueError, match="naive"):
        UTCDateTime().process_bind_param(datetime(2026, 1, 1), None)  # type: ignore[arg-type]


def test_sqlite_engine_uses_wal_and_foreign_keys(tmp_path: Path) -> None:
    engine = make_engine(f"sqlite:///{tmp_path / 'sub' / 'x.db'}")
    try:
        with engine.connect() as conn:
            assert conn.execute(text("PRAGMA journal_mode")).scalar() == "wal"
            assert conn.execute(text("PRAGMA foreign_keys")).scalar() == 1
        assert (tmp_path / "sub").is_dir()
    finally:
        engine.dispose()


def test_upgrade_downgrade_upgrade(tmp_path: Path) -> None:
    url = f"sqlite:///{tmp_path / 'm.db'}"
    upgrade_to_head(url)
    engine = make_engine(url)
    try:
        assert current_revision(engine) == HEAD
        assert set(inspect(engine).get_table_names()) >= set(Base.metadata.tables)
        command.downgrade(alembic_config(url), "base")
        assert current_revision(engine) is None
        engine.dispose()
        assert set(inspect(engine).get_table_names()) == {"alembic_version"}
        upgrade_to_head(url)
        assert current_revision(engine) == HEAD
    finally:
        engine.dispose()


def test_upgrade_from_0001_keeps_the_stored_trials(tmp_path: Path) -> None:
    """A database made by the first schema gains the later metrics (0, or NULL where not measured) and keeps
    every trial."""
    url = f"sqlite:///{tmp_path / 'old.db'}"
    command.upgrade(alembic_config(url), "0001")
    engine = make_engine(url)
    try:
        with engine.begin() as conn:
            conn.execute(
                text(
                    "INSERT INTO participants (id, code, notes, created) VALUES (1, 'P01', '', '2026-01-01')"
                )
            )
            conn.execute(
                text(
                    "INSERT INTO trials (id, participant_id, method, order_index, seed, settings, started_at,"
                    " status) VALUES (1, 1, 'proactive', 0, 7, '{}', '2026-01-01', 'completed')"
                )
            )
            later = (
                "time_moving_s",
                "mean_speed_scale",
                *_SAFETY_0004,
                *_BUDGET_0005,
                *_PERSON_0006,
                *_PFL_0007,
                *_CHOICES_0008,
            )
            cols = [c for c in METRIC_COLUMNS if c not in later]
            conn.execute(
                text(
                    f"INSERT INTO trial_metrics (trial_id, {', '.join(cols)}) "
                    f"VALUES (1, {', '.join('3' for _ in cols)})"
                )
            )
        upgrade_to_head(url)
        assert current_revision(engine) == HEAD
        with engine.connect() as conn:
            row = conn.execute(
                text("SELECT completed_tasks, time_moving_s, mean_speed_scale FROM trial_metrics")
            )
            assert [tuple(r) for r in row] == [(3, 0.0, 0.0)]
            safety = conn.execute(text(f"SELECT {', '.join(_SAFETY_0004)} FROM trial_metrics"))
            assert [tuple(r) for r in safety] == [(0, 0.0, 0, 0, None)]  # not measured: 0, and NULL
            budget = conn.execute(text(f"SELECT {', '.join(_BUDGET_0005)} FROM trial_metrics"))
            assert [tuple(r) for r in budget] == [(None,) * 12]  # no time budget kept then: unknown, not 0
            person = conn.execute(text(f"SELECT {', '.join(_PERSON_0006)} FROM trial_metrics"))
            assert [tuple(r) for r in person] == [(None, None)]
            pfl = conn.execute(text(f"SELECT {', '.join(_PFL_0007)} FROM trial_metrics"))
            assert [tuple(r) for r in pfl] == [(None,) * 5]  # judged by another judge then: unknown, not 0
            choices = conn.execute(text(f"SELECT {', '.join(_CHOICES_0008)} FROM trial_metrics"))
            assert [tuple(r) for r in choices] == [(None,) * 4]  # no candidate weighed then: unknown, not 0
            keys = conn.execute(text("SELECT id, trial_key, setting_label FROM trials"))
            assert [tuple(r) for r in keys] == [(1, None, None)]
    finally:
        engine.dispose()


def test_upgrade_of_an_unreachable_database_says_which() -> None:
    url = "postgresql+psycopg://nobody:secret@127.0.0.1:1/none?connect_timeout=2"
    with pytest.raises(DatabaseError, match=r"127\.0\.0\.1:1") as info:
        upgrade_to_head(url)
    assert "secret" not in str(info.value)


def test_migrations_ship_inside_the_package() -> None:
    """A wheel install carries them: they live under the package and the package data lists them."""
    import tomllib

    import app
    from app.study.db import MIGRATIONS_DIR

    package = Path(app.__file__).resolve().parent
    assert MIGRATIONS_DIR.is_relative_to(package) and (MIGRATIONS_DIR / "env.py").is_file()
    assert list((MIGRATIONS_DIR / "versions").glob("*.py"))
    pyproject = tomllib.loads((package.parent / "pyproject.toml").read_text())
    assert "migrations/**/*" in pyproject["tool"]["setuptools"]["package-data"]["app"]
