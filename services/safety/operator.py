"""The operator's reset token: a secret file only the operator's account can read."""

from __future__ import annotations

import hmac
import os
import secrets
from pathlib import Path

TOKEN_ENV = "TETHER_OPERATOR_TOKEN_FILE"


def token_path(configured: str | None = None) -> Path:
    if configured:
        return Path(configured).expanduser()
    if env := os.environ.get(TOKEN_ENV):
        return Path(env).expanduser()
    return Path.home() / ".config" / "tether" / "operator-token"


def ensure_token(path: Path) -> str:
    """Read the token, creating it (mode 0600) on first start."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w") as f:
            f.write(secrets.token_hex(24) + "\n")
    return read_token(path)


def read_token(path: Path) -> str:
    return path.read_text().strip()


def token_matches(expected: str, given: str) -> bool:
    return bool(expected) and hmac.compare_digest(expected.encode(), given.strip().encode())
