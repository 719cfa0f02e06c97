"""Engines, sessions and migrations of the study database.

SQLite (a file in ``Settings.data_dir``) by default, with WAL journaling, foreign keys on and a busy timeout;
any SQLAlchemy URL through ``HRC_DATABASE_URL`` (PostgreSQL: ``postgresql+psycopg://user@host/db``).
Nothing here runs at import time: engines are built by :func:`make_engine`.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.engine import make_url
from sqlalchemy.orm import Session, sessionmaker

log = logging.getLogger(__name__)

#: Alembic's script directory, shipped inside the package (so a wheel install can migrate too).
MIGRATIONS_DIR = Path(__file__).resolve().parents[1] / "migrations"
#: ``alembic.ini`` of a repository checkout (for the ``alembic`` command line); optional.
ALEMBIC_INI = Path(__file__).resolve().parents[2] / "alembic.ini"

SQLITE_BUSY_TIMEOUT_MS = 10_000


class DatabaseError(RuntimeError):
    """The study database could not be opened or migrated; the message says which URL and what to do."""


def default_database_url(settings: Any = None) -> str:
    """The database URL of ``settings`` (default: ``Settings()`` from the environment)."""
    if settings is None:
        from app.config import Settings

        settings = Settings()
    return settings.resolved_database_url()


def _is_sqlite(url: str) -> bool:
    return make_url(url).get_backend_name() == "sqlite"


def _ensure_sqlite_dir(url: str) -> None:
    database = make_url(url).database
    if database and database != ":memory:" and not database.startswith("file:"):
        Path(database).expanduser().parent.mkdir(parents=True, exist_ok=True)


def _sqlite_on_connect(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    try:
        cursor.execute("PRAGMA journal_mode=WAL")
        cursor.execute("PRAGMA foreign_keys=ON")
        cursor.execute("PRAGMA synchronous=NORMAL")
        cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    finally:
        cursor.close()


def make_engine(url: str | None = None, *, echo: bool = False) -> Engine:
    """Build an engine for ``url`` (default: the settings' URL).

    SQLite: creates the file's directory, turns on WAL, foreign keys, ``synchronous=NORMAL`` (durable at
    every WAL checkpoint, safe against a killed process) and a busy timeout so that several processes may
    share the file. Other backends: ``pool_pre_ping`` so that a restarted server is reconnected.
    """
    url = url or default_database_url()
    if _is_sqlite(url):
        _ensure_sqlite_dir(url)
        engine = create_engine(url, echo=echo, connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000})
        event.listen(engine, "connect", _sqlite_on_connect)
    else:
        engine = create_engine(url, echo=echo, pool_pre_ping=True)
    return engine


def session_factory(engine: Engine) -> sessionmaker[Session]:
    """A session factory bound to ``engine`` (objects stay readable after commit)."""
    return sessionmaker(engine, expire_on_commit=False)


def alembic_config(url: str | None = None) -> Any:
    """An Alembic ``Config`` for the migrations in :data:`MIGRATIONS_DIR`, targeting ``url``."""
    from alembic.config import Config

    cfg = Config(str(ALEMBIC_INI)) if ALEMBIC_INI.is_file() else Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    cfg.set_main_option("sqlalchemy.url", (url or default_database_url()).replace("%", "%%"))
    # env.py must not reconfigure the application's logging when called from code.
    cfg.attributes["configure_logger"] = False
    return cfg


def upgrade_to_head(url: str | None = None) -> None:
    """Migrate the database at ``url`` (default: the settings' URL) to the newest revision.

    Raises:
        DatabaseError: the migrations are missing or the database cannot be reached or migrated.
    """
    from alembic import command
    from sqlalchemy.exc import SQLAlchemyError

    if not (MIGRATIONS_DIR / "env.py").is_file():
        raise DatabaseError(
            f"Alembic migrations not found at {MIGRATIONS_DIR}; the installation is incomplete: "
            "reinstall the package"
        )
    url = url or default_database_url()
    if _is_sqlite(url):
        _ensure_sqlite_dir(url)
    try:
        command.upgrade(alembic_config(url), "head")
    except SQLAlchemyError as exc:
        safe = make_url(url).render_as_string(hide_password=True)
        raise DatabaseError(f"cannot migrate the study database {safe}: {exc}") from exc
    log.info("study database at head: %s", make_url(url).render_as_string(hide_password=True))


def current_revision(engine: Engine) -> str | None:
    """The Alembic revision the database is at (None for an empty database)."""
    from alembic.migration import MigrationContext

    with engine.connect() as conn:
        return MigrationContext.configure(conn).get_current_revision()
