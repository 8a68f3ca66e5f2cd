"""The e-stop latch file is on disk before save() returns (the file, then the directory holding its
name), and a safety process that dies while syncing it restarts latched."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import msgspec
import pytest

from schemas.safety import ControlMode, EstopState
from services.safety.latch import EstopLatch, write_durably
from services.safety.modes import ModeFile


def test_save_renames_the_file_into_place_then_syncs_it_and_the_directory(
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
    assert events == ["replace", "fsync estop.json", "fsync state"]
    monkeypatch.undo()
    assert EstopLatch("secret", state).state.latched


# A safety process that latches (or changes the mode) and dies in the sync that follows: the robot
# was told before the file was written, so the file must read as what was told once the process is
# gone, or a restarted safety would let the robot move again without an operator.
DIES_WHILE_SYNCING = """
import os, sys
from pathlib import Path
from schemas.safety import ControlMode
from services.safety.latch import EstopLatch
from services.safety.modes import ModeFile

state, mode = Path(sys.argv[1]), Path(sys.argv[2])
latch, modes = EstopLatch("secret", state), ModeFile(mode)
assert not latch.state.latched and modes.mode is ControlMode.AUTONOMOUS
latch.trigger("operator", "test", 1.0)
modes.set(ControlMode.SUPERVISED, "operator", 1.0)
os.fsync = lambda fd: os._exit(9)  # killed while the disk syncs
latch.save() if sys.argv[3] == "latch" else modes.save()
"""


@pytest.mark.parametrize("what", ["latch", "mode"])
def test_safety_dying_while_it_syncs_the_state_restarts_in_the_state_it_told(tmp_path: Path, what: str) -> None:
    state, mode = tmp_path / "estop.json", tmp_path / "mode.json"
    write_durably(state, msgspec.json.encode(EstopState(latched=False)))  # an install's first file
    ModeFile(mode).save()  # autonomous, written down
    run = subprocess.run(
        [sys.executable, "-c", DIES_WHILE_SYNCING, str(state), str(mode), what],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 9, run.stderr
    if what == "latch":
        assert EstopLatch("secret", state).state.latched
    else:
        assert ModeFile(mode).mode is ControlMode.SUPERVISED


# Mode changes saved from this many threads at once (the safety node answers set_mode on its workers).
SAVERS = 8
SAVES = 150


def test_modes_set_and_saved_from_many_threads_at_once_leave_the_latest_on_disk(tmp_path: Path) -> None:
    path = tmp_path / "mode.json"
    modes = ModeFile(path)
    start = threading.Barrier(SAVERS)
    failures: list[BaseException] = []

    def operator(number: int) -> None:
        start.wait()
        for i in range(SAVES):
            modes.set(list(ControlMode)[(number + i) % len(ControlMode)], f"operator {number}", float(i))
            try:
                modes.save()
            except OSError as exc:  # one save's rename finding the shared temporary file gone
                failures.append(exc)

    savers = [threading.Thread(target=operator, args=(n,)) for n in range(SAVERS)]
    for saver in savers:
        saver.start()
    for saver in savers:
        saver.join()
    assert not failures, failures[:3]
    # What a restart reads is the last state set, not an older one written after it.
    assert ModeFile(path).state == modes.state
