"""Progress of long work on recordings (reading, checking, replaying) on stderr, never on stdout.

Shown when stderr is a terminal, or with --progress; --no-progress hides it. rich.progress is imported
only when a bar is shown.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager, suppress
from pathlib import Path, PosixPath
from typing import IO, TYPE_CHECKING, Annotated, Any, TypeVar

import typer
from rich.console import Console

if TYPE_CHECKING:
    from rich.progress import Progress

T = TypeVar("T")

BATCH = 1000  # items counted at once
REPORT_BYTES = 1 << 18  # bytes read counted at once

ProgressOpt = Annotated[
    bool | None,
    typer.Option(
        "--progress/--no-progress",
        help="Show progress on stderr (default: when stderr is a terminal); stdout stays the output's.",
        show_default=False,
    ),
]


class Task:
    """One line of the progress display, or nothing when progress is not shown."""

    def __init__(self, progress: Progress | None = None, task_id: Any = None) -> None:
        self._progress = progress
        self._id = task_id

    def advance(self, amount: float) -> None:
        if self._progress is not None:
            self._progress.advance(self._id, amount)

    def done(self) -> None:
        """Mark it complete (an open-ended one too)."""
        if self._progress is not None:
            (task,) = (t for t in self._progress.tasks if t.id == self._id)
            total = task.total or 1  # an open-ended one: 1 of 1
            self._progress.update(self._id, total=total, completed=total)


class Bar:
    """The progress display of one command: lines added as the work goes on; without a display, each
    call does nothing (the work is the same)."""

    def __init__(self, progress: Progress | None = None) -> None:
        self._progress = progress

    @property
    def shown(self) -> bool:
        return self._progress is not None

    def task(self, description: str, total: float | None) -> Task:
        """A new line; `total` None for work of unknown length (a moving bar and the time taken)."""
        if self._progress is None:
            return Task()
        return Task(self._progress, self._progress.add_task(description, total=total))

    @contextmanager
    def step(self, description: str) -> Iterator[Task]:
        """Work of unknown length, complete when the block ends."""
        task = self.task(description, None)
        yield task
        task.done()

    def track(self, items: Iterable[T], total: int, description: str) -> Iterator[T]:
        """`items` as they are used, counted on a new line (in batches: a recording has millions)."""
        if self._progress is None:
            yield from items
            return
        task = self.task(description, total)
        used = 0
        for item in items:
            yield item
            used += 1
            if used == BATCH:
                task.advance(used)
                used = 0
        task.advance(used)

    @contextmanager
    def reading(self, paths: Sequence[Path]) -> Iterator[Sequence[Path]]:
        """`paths`, each counting on one "reading" line the bytes read from it when it is opened for
        reading in binary; the line is complete when the block ends (a reader may stop before the
        file's end, at its summary)."""
        if self._progress is None:
            yield paths
            return
        total = 0
        for path in paths:
            with suppress(OSError):  # the reader says what is wrong with it
                total += path.stat().st_size
        names = paths[0].name if len(paths) == 1 else f"{len(paths)} files"
        task = self.task(f"reading {names}", total)
        watched = [WatchedPath(path) for path in paths]
        for path in watched:
            path.on_read = task.advance
        yield watched
        task.done()


class WatchedPath(PosixPath):
    """A path whose binary reading streams tell `on_read` how many bytes each read returned."""

    on_read: Callable[[int], None] | None = None

    def open(self, mode: str = "r", *args: Any, **kwargs: Any) -> Any:  # type: ignore[override]
        stream = super().open(mode, *args, **kwargs)
        if self.on_read is None or mode not in ("rb", "br"):
            return stream
        return CountingReader(stream, self.on_read)


class CountingReader:
    """A binary stream that tells `on_read` how many bytes were read, every REPORT_BYTES or so (an MCAP
    reader reads a few bytes at a time: a record's opcode, its length, then its content)."""

    def __init__(self, stream: IO[bytes], on_read: Callable[[int], None]) -> None:
        self._stream = stream
        self._on_read = on_read
        self._unreported = 0

    def read(self, size: int = -1) -> bytes:
        data = self._stream.read(size)
        self._count(len(data))
        return data

    def readinto(self, buffer: Any) -> int:
        count: int = self._stream.readinto(buffer)  # type: ignore[attr-defined]
        self._count(count or 0)
        return count

    def _count(self, size: int) -> None:
        self._unreported += size
        if self._unreported >= REPORT_BYTES:
            self._on_read(self._unreported)
            self._unreported = 0

    def close(self) -> None:
        self._on_read(self._unreported)
        self._unreported = 0
        self._stream.close()

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)

    def __enter__(self) -> CountingReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@contextmanager
def progress_bar(shown: bool | None) -> Iterator[Bar]:
    """A Bar on stderr when `shown` (--progress), or when stderr is a terminal and `shown` is None;
    else one that shows nothing. The lines stay on the screen when the work ends."""
    if shown is False or (shown is None and not sys.stderr.isatty()):
        yield Bar()
        return
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn, TimeElapsedColumn

    console = Console(stderr=True, force_terminal=True if shown else None, soft_wrap=True)
    columns = (TextColumn("{task.description}"), BarColumn(), TaskProgressColumn(), TimeElapsedColumn())
    with Progress(*columns, console=console) as progress:
        yield Bar(progress)
