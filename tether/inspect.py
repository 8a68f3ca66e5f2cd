"""`tether inspect FILE`: an incident's timeline as a table, and a top-down map with --png."""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console
from rich.table import Table
from rich.text import Text

from schemas.world import KeepOut, World
from services.recorder.mapview import draw_map, estop_points, track_of, vetoed_goals
from services.recorder.reader import RecordingError, RecordingFile
from services.recorder.recorded import recorded_policy, recorded_world
from services.recorder.timeline import Level, RobotState, Row, Timeline, build_timeline
from services.worldmodel import DEFAULT_WORLD, WorldFileError, load_world
from tether.output import literal
from tether.progress import Bar, ProgressOpt, progress_bar
from tether.recordings import (
    FilesArg,
    RobotKeyOpt,
    console,
    fail,
    key_matcher,
    open_recording,
    printable,
    robot_key_of,
    shown,
)

out = Console()

# The key column is shown from this width on; output that is not a terminal gets PIPE_WIDTH.
WIDE = 140
PIPE_WIDTH = 180
LEVEL_STYLES = {Level.INFO: "", Level.GOOD: "green", Level.WARN: "yellow", Level.BAD: "red"}


def inspect(
    files: FilesArg,
    png: Annotated[
        Path | None, typer.Option("--png", help="Also draw a top-down map of the run into this PNG file.")
    ] = None,
    as_json: Annotated[
        bool, typer.Option("--json", help="Print the rows as one JSON object, or the error as one (exit 2).")
    ] = False,
    key_expr: Annotated[
        str | None,
        typer.Option(
            "--keys",
            help="Only rows about keys this Zenoh key expression matches (the key a command went to, or the key "
            "it was recorded on); relative ones (cmd/**) are under the robot's prefix.",
        ),
    ] = None,
    everything: Annotated[
        bool,
        typer.Option(
            "--all", help="List every message, also odometry, joint states, heartbeats, perception and feedback."
        ),
    ] = False,
    world: Annotated[
        str | None,
        typer.Option("--world", help="The world to draw when the recording carries none (a file or a bundled name)."),
    ] = None,
    robot_key_file: RobotKeyOpt = None,
    progress: ProgressOpt = None,
) -> None:
    """Show what happened in a recording: plan, steps, commands, safety decisions, e-stops, robot state.

    Odometry, heartbeats and other fast streams only set each row's robot state, unless they change something.
    Messages that are not safety's are rows of their own; with --robot-key their MACs are checked too. The
    e-stop column shows "?" where the latch is unknown (heartbeats of several senders at once, without the key).

    Exit 0; 2 for a missing or non-MCAP file, files that are not consecutive parts of one recording, a bad
    --keys or --robot-key, or a map that cannot be written.
    A file cut short is inspected as far as it is whole.
    """
    robot_key = robot_key_of(robot_key_file, as_json)
    with progress_bar(progress) as bar:
        recording = open_recording(files, bar=bar, as_json=as_json)
        with bar.step("building the timeline"):
            timeline = build_timeline(recording, everything, robot_key)
        rows = timeline.rows
        if key_expr is not None:
            rows = select(rows, recording.robot, key_expr, as_json)
        if png is not None:
            write_map(png, recording, timeline, world, bar, as_json)
    if as_json:
        print(json.dumps(as_document(recording, timeline, rows)))
        return
    # A terminal its own width; a file or a pager room for every column, or COLUMNS if set (read now:
    # `out` took its width when it was made).
    screen = out if out.is_terminal else Console() if "COLUMNS" in os.environ else Console(width=PIPE_WIDTH)
    screen.print(table(recording, timeline, rows, screen.width))


def select(rows: list[Row], robot: str, expr: str, as_json: bool = False) -> list[Row]:
    """The rows about keys `expr` matches: the key they are about or the one they were recorded on."""
    match = key_matcher(robot, expr, as_json)
    return [row for row in rows if match(row.key) or match(row.source)]


def write_map(
    png: Path,
    recording: RecordingFile,
    timeline: Timeline,
    world_name: str | None,
    bar: Bar | None = None,
    as_json: bool = False,
) -> None:
    world, keep_out = map_world(recording, world_name)
    robot = recording.robot or "unknown"
    title = printable(f"{recording.name} — robot {robot}" + ("" if world is not None else " (no world file)"))
    track, vetoed, estops = track_of(recording), vetoed_goals(timeline.rows), estop_points(timeline.rows)
    try:
        with (bar or Bar()).step("drawing the map"), warnings.catch_warnings():
            # Matplotlib names each character its font lacks in a warning, the character itself
            # included: a name in the file holding ESC would reach the terminal as it is.
            warnings.filterwarnings("ignore", message="Glyph .* missing from font")
            draw_map(png, title, world, keep_out, track, vetoed, estops)
    except OSError as exc:
        fail(f"cannot write the map to {png}: {exc.strerror or exc}", as_json=as_json)
    console.print(f"map written to {shown(png)}", highlight=False)


def map_world(recording: RecordingFile, world_name: str | None) -> tuple[World | None, list[KeepOut]]:
    """The world to draw and the keep-out zones in force: the recorded world and policy, else `--world`,
    else the bundled default, each with a note saying which."""
    try:
        world = recorded_world(recording)
    except RecordingError as exc:
        name = world_name or DEFAULT_WORLD
        try:
            world = load_world(name)
        except WorldFileError as error:
            said = shown(f"{exc}; and --world {name}: {error}; the map shows no world")
            console.print(f"[yellow]{said}[/]", highlight=False)
            return None, []
        console.print(f"[yellow]{shown(f'{exc}; the map shows the world {name!r} instead')}[/]", highlight=False)
        return world, list(world.keep_out)
    try:
        return world, list(recorded_policy(recording, world).limits.keep_out)
    except RecordingError as exc:
        console.print(f"[yellow]{shown(exc)}; the map shows the world file's keep-out zones only[/]", highlight=False)
        return world, list(world.keep_out)


def as_document(recording: RecordingFile, timeline: Timeline, rows: list[Row]) -> dict[str, Any]:
    return {
        "file": str(recording.path),
        "parts": [str(part) for part in recording.files],
        "robot": recording.robot,
        "complete": recording.complete,
        "problem": recording.problem,
        "start_ns": timeline.start_ns,
        "duration": timeline.duration,
        "messages": timeline.messages,
        "rows": [row.as_json() for row in rows],
    }


def _num(value: float | None, digits: int = 2) -> str:
    if value is None:
        return "-"
    text = f"{value:.{digits}f}"
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text  # no "-0.00"


def _pose(state: RobotState) -> str:
    if state.x is None or state.y is None:
        return "-"
    heading = f" {_num(math.degrees(state.yaw), 0)}°" if state.yaw is not None else ""
    return f"{_num(state.x)}, {_num(state.y)}{heading}"


def _safety(state: RobotState) -> Text:
    scale = f", {_num(state.speed_scale, 1)}" if state.speed_scale is not None else ""
    if state.estop is None:
        return Text("?" + scale, style="dim")
    return Text("LATCHED" + scale, style="bold red") if state.estop else Text("ok" + scale)


def table(recording: RecordingFile, timeline: Timeline, rows: list[Row], width: int) -> Table:
    """The rows with the robot's state at each; the key column only when there is room for it. Every
    text a file gave (keys, reasons, names) has its control characters escaped here, where rows reach
    the screen."""
    where = f"{recording.name}: robot {recording.robot or '?'}, {timeline.duration:.1f} s, "
    where += f"{timeline.messages} messages, {len(rows)} rows"
    result = Table(title=literal(printable(where)), title_justify="left")
    result.add_column("t (s)", justify="right", no_wrap=True)
    result.add_column("kind", no_wrap=True)
    wide = width >= WIDE
    if wide:
        result.add_column("key", overflow="fold", max_width=28)
    result.add_column("what happened", overflow="fold", ratio=1)
    result.add_column("x, y, heading", overflow="fold")
    result.add_column("m/s", justify="right", overflow="fold")
    result.add_column("e-stop, scale", overflow="fold")
    for row in rows:
        style = LEVEL_STYLES[row.level]
        state = row.state
        key = [Text(printable(row.key), style="dim")] if wide else []
        result.add_row(
            f"{row.t:.2f}",
            Text(str(row.kind), style=style),
            *key,
            Text(printable(row.text), style=style),
            _pose(state),
            _num(state.speed),
            _safety(state),
        )
    return result
