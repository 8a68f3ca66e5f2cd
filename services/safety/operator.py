"""The operator's reset token: a secret file only the operator's account can read."""

from __future__ import annotations

import contextlib
import errno
import hmac
import os
import secrets
from pathlib import Path

import msgspec

from schemas.safety import EstopState

TOKEN_ENV = "TETHER_OPERATOR_TOKEN_FILE"
# The token is 48 hex digits; a file much larger than that is something else.
MAX_TOKEN_BYTES = 4096


def token_path(configured: str | None = None) -> Path:
    if configured:
        return Path(configured).expanduser()
    if env := os.environ.get(TOKEN_ENV):
        return Path(env).expanduser()
    return Path.home() / ".config" / "tether" / "operator-token"


def ensure_token(path: Path, latch_file: Path | None = None) -> str:
    """Read the token, creating it (mode 0600) on first start, and then also `latch_file`, unlatched:
    a fresh install starts usable. Later, a latch file missing beside an existing token means it was
    lost, and safety starts latched (fail closed). The latch file is written before the token, so a
    crash between the two leaves no token and the next start tries again."""
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        if latch_file is not None:
            unlatched = EstopState(latched=False, source="install", reason="first start")
            _write_new(latch_file, msgspec.json.encode(unlatched))
        _write_new(path, (secrets.token_hex(24) + "\n").encode())
    return read_token(path)


def _write_new(path: Path, data: bytes) -> None:
    """Write `path` (mode 0600) only if it does not exist, whole or not at all: another safety starting
    at the same moment makes it too, and the first one wins."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        with contextlib.suppress(FileExistsError):
            os.link(tmp, path)  # atomic, never replaces
    finally:
        tmp.unlink(missing_ok=True)


def read_token(path: Path) -> str:
    """The token in `path`. A file that is no token (not UTF-8 text, or more than MAX_TOKEN_BYTES:
    /dev/zero would be read without end) is refused with an OSError, as one that cannot be read."""
    with path.open("rb") as file:
        data = file.read(MAX_TOKEN_BYTES + 1)
    if len(data) > MAX_TOKEN_BYTES:
        raise OSError(errno.EFBIG, f"over {MAX_TOKEN_BYTES} bytes: not a token file", str(path))
    try:
        return data.decode().strip()
    except UnicodeDecodeError:
        raise OSError(errno.EINVAL, "not text: not a token file", str(path)) from None


def token_matches(expected: str, given: str) -> bool:
    return bool(expected) and hmac.compare_digest(expected.encode(), given.strip().encode())
