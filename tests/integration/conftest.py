"""Integration fixtures: a real PostgreSQL server on loopback, and study databases on SQLite and PostgreSQL.

``postgres_server`` (session-scoped) runs ``initdb`` and ``pg_ctl`` from ``/usr/lib/postgresql/*/bin`` on a
temporary data directory (as the ``postgres`` user when the tests run as root), listening on 127.0.0.1 on a
free port, and stops it at the end. It skips with the reason when the binaries are missing (install the
Debian package ``postgresql``: ``scripts/system-deps.sh`` does) or the server cannot start.
``db_url`` is parametrised over ``sqlite`` and ``postgresql``: a fresh, empty database per test.
``elbow_free`` turns a work-cell file into the same cell with the elbow free (both of its IK branches), for
scenes made in the cells before they kept the elbow on home's side.
"""

from __future__ import annotations

import glob
import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from app.config import WorkCell, load_workcell

PG_START_TIMEOUT_S = 60
#: The cells' elbow limit (on home's side) and the elbow free, as their files write them.
ELBOW_KEPT = "q_min = [-6.2832, -6.2832, 0.0, -6.2832, -3.1416, -6.2832]"
ELBOW_FREE = "q_min = [-6.2832, -6.2832, -3.1416, -6.2832, -3.1416, -6.2832]"


@pytest.fixture(scope="session")
def elbow_free(tmp_path_factory: pytest.TempPathFactory) -> Callable[[Path], WorkCell]:
    """``elbow_free(path)``: the work cell of ``path`` with the elbow free."""

    def make(path: Path) -> WorkCell:
        text = path.read_text()
        assert ELBOW_KEPT in text, f"{path} no longer keeps the elbow as {ELBOW_KEPT!r}"
        out = tmp_path_factory.mktemp("cell") / "workcell.toml"
        out.write_text(text.replace(ELBOW_KEPT, ELBOW_FREE))
        return load_workcell(out)

    return make


@dataclass(frozen=True)
class PostgresServer:
    """A running server: connect as ``user`` without password on ``host:port``."""

    host: str
    port: int
    user: str

    def url(self, database: str) -> str:
        return f"postgresql+psycopg://{self.user}@{self.host}:{self.port}/{database}"

    def create_database(self) -> str:
        """Create a fresh database; returns its SQLAlchemy URL."""
        import psycopg

        name = f"hrc_test_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(
            host=self.host,
            port=self.port,
            user=self.user,
            dbname="postgres",
            autocommit=True,
            connect_timeout=10,
        ) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)


def _pg_bin_dir() -> Path | None:
    found = sorted(glob.glob("/usr/lib/postgresql/*/bin/initdb"), key=lambda p: int(Path(p).parts[4]))
    return Path(found[-1]).parent if found else None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _run(cmd: list[str], *, as_user: str | None, timeout_s: float) -> subprocess.CompletedProcess[str]:
    if as_user is not None:
        cmd = ["runuser", "-u", as_user, "--", *cmd]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)


@pytest.fixture(scope="session")
def postgres_server() -> Iterator[PostgresServer]:
    """A real PostgreSQL server for this test session (skips with the reason where it cannot start)."""
    bin_dir = _pg_bin_dir()
    if bin_dir is None:
        pytest.skip(
            "PostgreSQL server binaries not found under /usr/lib/postgresql/*/bin; install the Debian "
            "package `postgresql` (scripts/system-deps.sh does, as root)"
        )
    try:
        import psycopg  # noqa: F401
    except ImportError:
        pytest.skip("psycopg (3) is not installed in the venv; `pip install 'psycopg[binary]'`")
    as_user: str | None = None
    if os.geteuid() == 0:  # PostgreSQL refuses to run as root
        try:
            pw = pwd.getpwnam("postgres")
        except KeyError:
            pytest.skip("running as root and there is no `postgres` user to run the server as")
        if shutil.which("runuser") is None:
            pytest.skip("running as root and `runuser` is missing (needed to start PostgreSQL as `postgres`)")
        as_user = "postgres"
    base = Path(tempfile.mkdtemp(prefix="hrc-pg-"))
    data, sock = base / "data", base / "sock"
    sock.mkdir()
    if as_user is not None:
        for p in (base, sock):
            os.chown(p, pw.pw_uid, pw.pw_gid)
    user = "postgres" if as_user else pwd.getpwuid(os.geteuid()).pw_name
    port = _free_port()
    log = base / "server.log"
    started = False
    try:
        r = _run(
            [str(bin_dir / "initdb"), "-D", str(data), "-U", user, "-A", "trust", "-E", "UTF8", "--no-sync"],
            as_user=as_user,
            timeout_s=PG_START_TIMEOUT_S,
        )
        if r.returncode != 0:
            pytest.skip(f"initdb failed (rc {r.returncode}): {r.stderr.strip()[-500:]}")
        opts = (
            f"-p {port} -k {sock} -c listen_addresses=127.0.0.1 -c fsync=off -c synchronous_commit=off "
            "-c full_page_writes=off -c shared_buffers=16MB -c max_connections=40"
        )
        r = _run(
            [
                str(bin_dir / "pg_ctl"),
                "-D",
                str(data),
                "-l",
                str(log),
                "-o",
                opts,
                "-w",
                "-t",
                str(PG_START_TIMEOUT_S),
                "start",
            ],
            as_user=as_user,
            timeout_s=PG_START_TIMEOUT_S + 10,
        )
        if r.returncode != 0:
            tail = log.read_text(errors="replace")[-800:] if log.exists() else r.stderr
            pytest.skip(f"PostgreSQL did not start (pg_ctl rc {r.returncode}): {tail.strip()}")
        started = True
        yield PostgresServer(host="127.0.0.1", port=port, user=user)
    finally:
        if started:
            _run(
                [str(bin_dir / "pg_ctl"), "-D", str(data), "-m", "fast", "-w", "stop"],
                as_user=as_user,
                timeout_s=60,
            )
        shutil.rmtree(base, ignore_errors=True)


@pytest.fixture(params=["sqlite", pytest.param("postgresql", marks=pytest.mark.postgres)])
def db_url(request: pytest.FixtureRequest, tmp_path: Path) -> str:
    """A URL of a fresh, empty study database (no schema yet) on SQLite or on the PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{(tmp_path / 'study.db').as_posix()}"
    server: PostgresServer = request.getfixturevalue("postgres_server")
    return server.create_database()
