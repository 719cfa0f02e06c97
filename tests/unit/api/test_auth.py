"""Operator token: generation, storage (0600), constant-time check, 401 on every protected route."""

from __future__ import annotations

import stat
from collections.abc import Callable
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from app.api import auth
from app.api.auth import TokenError, bearer_token, ensure_api_token, tokens_match
from app.config import Settings

TOKEN = "env-token-0123456789abcdef"


def test_token_generated_once_stored_0600_and_reused(tmp_path: Path) -> None:
    s = Settings(_env_file=None, data_dir=tmp_path / "d", api_token=None)
    first = ensure_api_token(s)
    assert first.source == "generated"
    assert first.path == tmp_path / "d" / "api_token"
    assert stat.S_IMODE(first.path.stat().st_mode) == 0o600
    assert len(first.value) >= 40
    again = ensure_api_token(s)
    assert again.source == "file" and again.value == first.value
    assert first.value not in repr(first)  # the secret never ends up in a log line


def test_token_file_with_loose_mode_is_restricted(tmp_path: Path) -> None:
    path = tmp_path / "api_token"
    path.write_text("x" * 32 + "\n")
    path.chmod(0o644)
    tok = ensure_api_token(Settings(_env_file=None, data_dir=tmp_path))
    assert tok.value == "x" * 32
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_environment_token_wins_and_short_tokens_are_refused(tmp_path: Path) -> None:
    tok = ensure_api_token(Settings(_env_file=None, data_dir=tmp_path, api_token=TOKEN))
    assert tok.source == "environment" and tok.value == TOKEN and tok.path is None
    assert not (tmp_path / "api_token").exists()
    with pytest.raises(TokenError, match="shorter than"):
        ensure_api_token(Settings(_env_file=None, data_dir=tmp_path, api_token="short"))


def test_tokens_match_uses_compare_digest(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    real = auth.hmac.compare_digest

    def spy(a: bytes, b: bytes) -> bool:
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(auth.hmac, "compare_digest", spy)
    assert tokens_match(TOKEN, TOKEN)
    assert not tokens_match(TOKEN + "x", TOKEN)
    assert not tokens_match(None, TOKEN)
    assert len(calls) == 2


def test_bearer_token_parsing() -> None:
    assert bearer_token("Bearer abc") == "abc"
    assert bearer_token("bearer  abc ") == "abc"
    assert bearer_token("Basic abc") is None
    assert bearer_token("Bearer") is None
    assert bearer_token(None) is None


PROTECTED = [
    ("GET", "/api/info"),
    ("GET", "/api/participants"),
    ("POST", "/api/participants"),
    ("GET", "/api/participants/1"),
    ("PATCH", "/api/participants/1"),
    ("DELETE", "/api/participants/1"),
    ("GET", "/api/participants/1/method-order"),
    ("GET", "/api/sessions"),
    ("POST", "/api/sessions"),
    ("GET", "/api/sessions/1"),
    ("PATCH", "/api/sessions/1"),
    ("DELETE", "/api/sessions/1"),
    ("GET", "/api/trials"),
    ("POST", "/api/trials"),
    ("GET", "/api/trials/1"),
    ("GET", "/api/trials/1/events"),
    ("POST", "/api/trials/1/stop"),
    ("GET", "/api/robot"),
    ("GET", "/api/state"),
    ("POST", "/api/robot/estop"),
    ("POST", "/api/robot/reset"),
    ("GET", "/api/summary"),
    ("GET", "/api/summary/table.csv"),
    ("GET", "/api/summary/table.md"),
    ("GET", "/api/summary/boxplots.png"),
    ("GET", "/api/export/participants.csv"),
    ("GET", "/api/export/trials.csv"),
    ("GET", "/api/export/metrics.csv"),
    ("GET", "/api/export/events.csv"),
]


def test_every_api_route_is_listed_here(client: TestClient) -> None:
    ids = {"{participant_id}": "1", "{session_id}": "1", "{trial_id}": "1"}
    routes = set()
    for path, ops in client.app.openapi()["paths"].items():
        for key, value in ids.items():
            path = path.replace(key, value)
        routes |= {(m.upper(), path) for m in ops}
    assert routes == set(PROTECTED) | {("GET", "/api/health")}


def test_protected_routes_need_the_token(client: TestClient) -> None:
    for method, path in PROTECTED:
        missing = client.request(method, path)
        assert missing.status_code == 401, (method, path)
        assert missing.headers["www-authenticate"].startswith("Bearer")
        assert "token" in missing.json()["detail"]
        wrong = client.request(method, path, headers={"Authorization": "Bearer " + "x" * 30})
        assert wrong.status_code == 401, (method, path)
        assert wrong.json()["detail"] == "invalid operator token"
        basic = client.request(method, path, headers={"Authorization": "Basic dXNlcjpwdw=="})
        assert basic.status_code == 401, (method, path)


def test_health_is_open(client: TestClient) -> None:
    r = client.get("/api/health")
    assert r.status_code == 200
    assert r.json()["status"] == "ok" and r.json()["database"] == "ok"


def test_read_only_open_opens_get_but_not_changes(
    make_client: Callable[..., TestClient], settings: Settings, auth: dict[str, str]
) -> None:
    c = make_client(settings.model_copy(update={"read_only_open": True}))
    assert c.get("/api/participants").status_code == 200
    assert c.get("/api/robot").status_code == 200
    assert c.get("/api/export/trials.csv").status_code == 200
    assert c.post("/api/participants", json={"code": "P1"}).status_code == 401
    assert c.post("/api/robot/estop").status_code == 401
    assert c.post("/api/participants", json={"code": "P1"}, headers=auth).status_code == 201


def test_generated_token_protects_the_app(make_client: Callable[..., TestClient], tmp_path: Path) -> None:
    s = Settings(_env_file=None, data_dir=tmp_path / "gen", database_url=f"sqlite:///{tmp_path}/g.db")
    c = make_client(s)
    token = (tmp_path / "gen" / "api_token").read_text().strip()
    assert c.get("/api/participants").status_code == 401
    assert c.get("/api/participants", headers={"Authorization": f"Bearer {token}"}).status_code == 200


def test_serve_reports_a_bad_token_without_a_traceback(tmp_path, monkeypatch) -> None:
    from typer.testing import CliRunner

    from app.cli import app

    monkeypatch.setenv("HRC_API_TOKEN", "short")
    monkeypatch.setenv("HRC_DATA_DIR", str(tmp_path))
    res = CliRunner().invoke(app, ["serve"])
    assert res.exit_code == 2
    assert "shorter than" in res.output and "Traceback" not in res.output
