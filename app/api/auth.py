"""The operator token: generated and stored at first start, compared in constant time, checked per request.

Every ``/api`` route except ``/api/health`` needs ``Authorization: Bearer <token>``. The token comes from
``HRC_API_TOKEN`` when set; otherwise it is read from ``<data_dir>/api_token`` (file mode 0600), and generated
into that file at the first start. ``HRC_READ_ONLY_OPEN=true`` opens the read-only (GET) routes without a
token, for a trusted lab network; every route that changes something still needs it.
"""

from __future__ import annotations

import hmac
import logging
import os
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from app.config import Settings

logger = logging.getLogger(__name__)

TOKEN_FILE_NAME = "api_token"
#: Shortest token accepted from the environment or the token file (characters).
MIN_TOKEN_LENGTH = 16

TokenSource = Literal["environment", "file", "generated"]


class TokenError(RuntimeError):
    """The operator token could not be read or written; the message says which file and what to do."""


@dataclass(frozen=True, slots=True)
class ApiToken:
    """The operator token and where it came from.

    Attributes:
        value: The secret itself.
        source: ``environment`` (HRC_API_TOKEN), ``file`` (read from ``path``) or ``generated`` (written to
            ``path`` just now: the caller should show it to the operator once).
        path: The token file, or None when the token came from the environment.
    """

    value: str
    source: TokenSource
    path: Path | None

    def __repr__(self) -> str:  # never leak the secret into logs
        return f"ApiToken(source={self.source!r}, path={self.path!r})"


def token_path(settings: Settings) -> Path:
    """Where the generated token is stored: ``<data_dir>/api_token``."""
    return Path(settings.data_dir) / TOKEN_FILE_NAME


def generate_token() -> str:
    """A fresh random token (32 bytes of entropy, URL-safe base64, 43 characters)."""
    return secrets.token_urlsafe(32)


def _check_token_text(value: str, origin: str) -> str:
    value = value.strip()
    if len(value) < MIN_TOKEN_LENGTH:
        raise TokenError(
            f"the API token from {origin} is shorter than {MIN_TOKEN_LENGTH} characters; "
            "set a longer HRC_API_TOKEN or delete the token file to have one generated"
        )
    if any(c.isspace() for c in value):
        raise TokenError(f"the API token from {origin} contains whitespace; use a URL-safe token")
    return value


def _read_token_file(path: Path) -> str:
    try:
        mode = stat.S_IMODE(path.stat().st_mode)
        if mode & 0o077:
            logger.warning("token file %s had mode %o; restricting it to 0600", path, mode)
            path.chmod(0o600)
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise TokenError(f"cannot read the API token file {path}: {exc.strerror}") from exc
    return _check_token_text(text, str(path))


def _write_new_token(path: Path) -> str | None:
    """Create ``path`` with a new token, mode 0600, atomically; None if another process created it first."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TokenError(
            f"cannot create the data directory {path.parent} for the API token: {exc.strerror}; "
            "set HRC_DATA_DIR to a writable directory or set HRC_API_TOKEN"
        ) from exc
    value = generate_token()
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return None
    except OSError as exc:
        raise TokenError(
            f"cannot write the API token file {path}: {exc.strerror}; set HRC_API_TOKEN instead"
        ) from exc
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(value + "\n")
    return value


def ensure_api_token(settings: Settings) -> ApiToken:
    """The operator token: from ``HRC_API_TOKEN``, else the token file, else a new one written to the file.

    Raises:
        TokenError: the token is too short, or the file cannot be read or written.
    """
    if settings.api_token:
        return ApiToken(_check_token_text(settings.api_token, "HRC_API_TOKEN"), "environment", None)
    path = token_path(settings)
    if path.exists():
        return ApiToken(_read_token_file(path), "file", path)
    value = _write_new_token(path)
    if value is None:  # lost a race with another process: use theirs
        return ApiToken(_read_token_file(path), "file", path)
    logger.warning("generated a new API token and stored it in %s (mode 0600)", path)
    return ApiToken(value, "generated", path)


def tokens_match(given: str | None, expected: str) -> bool:
    """Constant-time comparison of a presented token with the expected one (False for None)."""
    if given is None:
        return False
    return hmac.compare_digest(given.encode("utf-8"), expected.encode("utf-8"))


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header value, or None when absent or malformed."""
    if not authorization:
        return None
    scheme, _, credentials = authorization.partition(" ")
    if scheme.lower() != "bearer" or not credentials.strip():
        return None
    return credentials.strip()
