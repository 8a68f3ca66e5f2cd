"""Log files' tails, printed for pytest to show when a test failed."""

from __future__ import annotations

from pathlib import Path


def print_tails(directory: Path, lines: int = 40) -> None:
    """The last `lines` lines of every *.log under `directory`, each under its path from there."""
    for log in sorted(directory.rglob("*.log")):
        tail = "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
        print(f"----- {log.relative_to(directory)} -----\n{tail}")
