"""The recorder across steps of the wall clock (NTP correcting a robot that booted with its clock wrong),
and over a long run: files rotated on time, their parts read back as one, a status that stays small."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas import keys
from services.recorder import recorder as recorder_module
from services.recorder.config import RecorderConfig
from services.recorder.mcapfile import Provenance, Recording
from services.recorder.reader import Recorded, RecordingError, join_recordings, read_recording
from services.recorder.recorder import Recorder
from services.runtime import encode

ROBOT = "r1"
KEY = f"{keys.prefix(ROBOT)}/a"
SECOND = 1_000_000_000
HOUR = 3600 * SECOND


class Clocks:
    """The wall clock, which NTP may step, and the monotonic clock, which only ever runs on."""

    def __init__(self) -> None:
        self.wall = 1_800_000_000 * SECOND
        self.monotonic = 7 * SECOND

    def run(self, seconds: float) -> None:
        self.wall += int(seconds * SECOND)
        self.monotonic += int(seconds * SECOND)


def recorder(out: Path, clocks: Clocks, max_file_seconds: float) -> Recorder:
    return Recorder(
        RecorderConfig(output_dir=str(out), max_file_seconds=max_file_seconds),
        Provenance(ROBOT),
        clock=lambda: clocks.wall,
        monotonic=lambda: clocks.monotonic,
    )


def numbers(messages: list[Recorded]) -> list[int]:
    return [json.loads(m.data)["i"] for m in messages]


def test_a_step_back_neither_holds_back_a_rotation_nor_parts_the_recording(tmp_path: Path) -> None:
    """The wall clock set back an hour mid-file: the file was not rotated for an hour (its age was
    negative), and the reader refused to join the parts, whose receive times overlap."""
    clocks = Clocks()
    rec = recorder(tmp_path, clocks, max_file_seconds=10.0)
    rec.record(KEY, encode({"i": 0}))
    clocks.run(4)
    clocks.wall -= HOUR
    rec.record(KEY, encode({"i": 1}))
    clocks.run(7)
    rec.tick()  # 11 s since the file started
    assert len(rec.files) == 2, "not rotated after 11 s of a 10 s limit"
    rec.record(KEY, encode({"i": 2}))
    clocks.run(11)
    rec.tick()
    rec.record(KEY, encode({"i": 3}))
    rec.finish()

    parts = [read_recording(path) for path in rec.files]
    assert len(parts) == 3
    # What makes the step visible in the files: the second part starts before the first one ends.
    assert min(m.log_time for m in parts[1].messages) < max(m.log_time for m in parts[0].messages)
    joined = join_recordings(parts[::-1])
    assert joined.files == rec.files
    assert numbers(joined.messages) == [0, 1, 2, 3], "in the order they were recorded"
    start = 1_800_000_000 * SECOND
    assert [m.log_time for m in joined.messages] == [
        start,
        start - HOUR + 4 * SECOND,
        start - HOUR + 11 * SECOND,
        start - HOUR + 22 * SECOND,
    ]


def test_a_step_forward_does_not_rotate_at_once(tmp_path: Path) -> None:
    clocks = Clocks()
    rec = recorder(tmp_path, clocks, max_file_seconds=10.0)
    rec.record(KEY, encode({"i": 0}))
    clocks.run(1)
    clocks.wall += HOUR
    rec.tick()
    assert len(rec.files) == 1, "rotated 1 s into a 10 s file"
    clocks.run(9)
    rec.tick()
    assert len(rec.files) == 2
    rec.finish()


def part(path: Path, number: int, log_times: list[int], elapsed_ns: int | None) -> Path:
    recording = Recording(path, ROBOT, part=number, run="run1", clock=lambda: 0, elapsed_ns=elapsed_ns)
    for i, at in enumerate(log_times):
        recording.record(KEY, encode({"i": i}), log_time=at)
    recording.finish()
    return path


def test_parts_that_do_not_follow_one_another_on_the_recorders_clock_are_refused(tmp_path: Path) -> None:
    first = part(tmp_path / "p0.mcap", 0, [HOUR, HOUR + SECOND], elapsed_ns=0)
    stepped = part(tmp_path / "p1.mcap", 1, [SECOND], elapsed_ns=10 * SECOND)
    assert numbers(join_recordings([read_recording(stepped), read_recording(first)]).messages) == [0, 1, 0]
    # Part 1 said to have started before part 0 did.
    late = part(tmp_path / "late.mcap", 0, [HOUR], elapsed_ns=5 * SECOND)
    early = part(tmp_path / "early.mcap", 1, [2 * HOUR], elapsed_ns=0)
    with pytest.raises(RecordingError, match=r"early\.mcap starts before .*late\.mcap on the recorder's own clock"):
        join_recordings([read_recording(late), read_recording(early)])
    # A part without the recorder's clock (not written by a recorder that keeps it): receive times decide.
    unclocked = part(tmp_path / "unclocked.mcap", 1, [SECOND], elapsed_ns=None)
    with pytest.raises(RecordingError, match="overlap in time"):
        join_recordings([read_recording(first), read_recording(unclocked)])


def test_the_status_names_the_latest_files_and_counts_every_one(tmp_path: Path) -> None:
    """A run rotating for months: every file's name was kept, and sent in every status reply."""
    clock = Clocks()
    rec = recorder(tmp_path, clock, max_file_seconds=1.0)
    files = 130
    for i in range(files):
        rec.record(KEY, encode({"i": i}))
        if i < files - 1:
            clock.run(1)
            rec.tick()
    status = rec.status()
    rec.finish()

    every = sorted(tmp_path.glob("*.mcap"))
    assert len(every) == files
    assert len(status.files) < files, "every file named"
    listed = recorder_module.FILES_LISTED
    assert len(status.files) == listed and status.files == [str(p) for p in every[-listed:]]
    assert status.path == status.files[-1] and status.messages == files
    assert rec.parts == files and rec.files == every[-listed:]
    assert rec.files_said().endswith(f"{every[-1]} (after {files - listed} earlier files)")
    last = read_recording(Path(status.path))
    assert last.metadata["tether"]["part"] == str(files - 1) and numbers(last.messages) == [files - 1]
    assert numbers(join_recordings([read_recording(p) for p in every]).messages) == list(range(files))
