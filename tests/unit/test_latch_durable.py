"""The e-stop latch file is on disk before save() returns: the file, then the directory holding its name."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from services.safety.latch import EstopLatch


def test_save_fsyncs_the_file_before_the_rename_and_the_directory_after(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    state = tmp_path / "state" / "estop.json"
    latch = EstopLatch("secret", state)
    latch.save()  # the first write makes the directory; the calls of a later save are watched
    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        target = Path(os.readlink(f"/proc/self/fd/{fd}"))
        events.append(f"fsync {target.name}")
        real_fsync(fd)

    def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        events.append("replace")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    latch.trigger("operator", "test", 1.0)
    latch.save()
    assert events == ["fsync estop.tmp", "replace", "fsync state"]
    monkeypatch.undo()
    assert EstopLatch("secret", state).state.latched
