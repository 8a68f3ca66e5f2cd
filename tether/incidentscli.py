"""`tether incidents`: safety's memory of what went wrong where (e-stops, trips, vetoes, near-misses,
failed grasps, drops, collisions), the caution zones it makes, and the operator's say over it.

Listing asks safety (`safety/incidents`); forgetting an incident or clearing a caution zone takes the
operator token (as `tether reset`), and in a secured deployment only the operator's identity may ask.
`show` adds the incident's timeline from the recording it is in (as `tether inspect`)."""

from __future__ import annotations

import datetime as dt
import json
import math
import time
from pathlib import Path
from typing import Annotated, Any, NoReturn

import msgspec
import typer
from rich.console import Console
from rich.table import Table

from schemas import keys
from schemas.common import fmt_point
from schemas.incidents import (
    ForgetAction,
    ForgetIncident,
    ForgetReply,
    Incident,
    IncidentKind,
    IncidentList,
    IncidentQuery,
)
from services.errors import CallError
from services.safety.hazards import ago, zone_reason
from services.safety.operator import read_token, token_path
from tether.client import EXIT_UNREACHABLE, operator_name
from tether.output import command_node, printable, shown

# Exit codes.
EXIT_OK = 0
EXIT_REFUSED = 2  # bad input, an unknown incident, a wrong token: safety said no
EXIT_NOT_FOUND = 2

CALL_TIMEOUT = 3.0
# `show`: the recording's rows this many seconds either side of the incident.
SHOW_WINDOW = 10.0

app = typer.Typer(no_args_is_help=False, invoke_without_command=True, add_completion=False)
console = Console(stderr=True, highlight=False)
out = Console(highlight=False)

JsonOpt = Annotated[bool, typer.Option("--json", help="Print one JSON object (show: the incident and its rows).")]
TokenFileOpt = Annotated[str | None, typer.Option("--token-file", help="The operator token file safety created.")]


def _fail(as_json: bool, why: str, code: int, **data: Any) -> NoReturn:
    if as_json:
        print(json.dumps({"ok": False, "error": why, **data}))
    else:
        console.print(shown(f"error: {why}"))
    raise typer.Exit(code)


def _ask(ctx: typer.Context, query: IncidentQuery, as_json: bool) -> IncidentList:
    with command_node(ctx, console) as node:
        try:
            answer: IncidentList = node.call(keys.INCIDENTS, query, timeout=CALL_TIMEOUT)
        except CallError as exc:
            _fail(as_json, f"safety unreachable: {exc}", EXIT_UNREACHABLE)
    return answer


def parse_since(text: str, now: float) -> float:
    """`--since`: a duration back from now (90s, 30m, 2h, 7d) or an ISO date or time (2026-11-20,
    2026-11-20T14:00); wall clock seconds. Raises ValueError naming what it reads."""
    value = text.strip()
    units = {"s": 1.0, "m": 60.0, "h": 3600.0, "d": 86400.0}
    if value and value[-1] in units:
        try:
            amount = float(value[:-1])
        except ValueError:
            amount = math.nan
        if math.isfinite(amount) and amount >= 0:
            return max(0.0, now - amount * units[value[-1]])
    try:
        when = dt.datetime.fromisoformat(value)
    except ValueError:
        raise ValueError(
            f"--since {text!r} is neither a duration (90s, 30m, 2h, 7d) nor a date or time (2026-11-20T14:00)"
        ) from None
    try:
        if when.tzinfo is None:
            when = when.astimezone()
        return max(0.0, when.timestamp())
    except (OverflowError, OSError, ValueError):
        raise ValueError(f"--since {text!r} is a date this computer cannot place in time") from None


def where(incident: Incident) -> str:
    return "where unknown" if incident.x is None or incident.y is None else fmt_point(incident.x, incident.y)


def local_time(stamp: float) -> str | None:
    """`stamp` (wall clock seconds) as an ISO time here; None for one no date can show (safety's answer
    is a peer's: a stamp from a broken clock or a hostile store file must not stop the listing)."""
    try:
        return dt.datetime.fromtimestamp(stamp).astimezone().isoformat(timespec="seconds")
    except (OverflowError, OSError, ValueError):
        return None


def incident_json(incident: Incident) -> dict[str, Any]:
    data: dict[str, Any] = msgspec.to_builtins(incident)
    # Always present, also when safety did not know the pose or the time is no date (None then).
    data.setdefault("x", None)
    data.setdefault("y", None)
    data["time"] = local_time(incident.stamp)
    return data


# The options that set each field of an IncidentQuery.
QUERY_OPTIONS = {"x": "--near", "y": "--near", "radius": "--radius", "since": "--since", "limit": "--limit"}


def _list(
    ctx: typer.Context,
    near: list[float] | None,
    radius: float,
    kind: list[str] | None,
    since: str | None,
    limit: int,
    as_json: bool,
) -> None:
    now = time.time()
    try:
        kinds = [IncidentKind(k.strip().lower()) for k in kind or []]
    except ValueError:
        known = ", ".join(k.value for k in IncidentKind)
        _fail(as_json, f"unknown kind in {kind}; kinds are {known}", EXIT_REFUSED)
    try:
        since_t = parse_since(since, now) if since else 0.0
        fields: dict[str, Any] = {"kinds": kinds, "since": since_t, "limit": limit, "radius": radius}
        if near is not None:
            fields["x"], fields["y"] = near
        query = msgspec.convert(fields, IncidentQuery)
    except msgspec.ValidationError as exc:  # it names the query's field (`$.x`), not the option given
        field = str(exc).rpartition("`$.")[2].rstrip("`")
        _fail(as_json, f"{QUERY_OPTIONS.get(field, field)}: {exc}", EXIT_REFUSED)
    except ValueError as exc:
        _fail(as_json, str(exc), EXIT_REFUSED)
    answer = _ask(ctx, query, as_json)
    if as_json:
        print(
            json.dumps(
                {
                    "ok": True,
                    "incidents": [incident_json(i) for i in answer.incidents],
                    "total": answer.total,
                    "zones": msgspec.to_builtins(answer.zones),
                    "store": answer.store,
                }
            )
        )
        raise typer.Exit(EXIT_OK)
    if answer.store:
        console.print(shown(f"warning: the incident store has a fault: {answer.store}"), style="yellow")
    if not answer.incidents:
        out.print("no incidents" + (" match" if kinds or since or near is not None else " remembered"))
    else:
        table = Table(title=f"{len(answer.incidents)} of {answer.total} incidents, newest first", title_justify="left")
        for column in ("id", "when", "kind", "where", "plan step", "reason"):
            table.add_column(column, overflow="fold", ratio=1 if column == "reason" else None)
        for incident in answer.incidents:
            step = incident.label or ("" if incident.step is None else str(incident.step))
            kind_text = str(incident.kind) + (f" ({incident.source})" if incident.source else "")
            kind_text += " [cleared]" if incident.cleared else ""
            table.add_row(
                str(incident.id),
                ago(incident.stamp, now),
                shown(kind_text),
                where(incident),
                shown(step),
                shown(incident.reason),
            )
        out.print(table)
    for zone in answer.zones:
        out.print(shown(zone_reason(zone)))
    raise typer.Exit(EXIT_OK)


@app.callback()
def incidents(
    ctx: typer.Context,
    near: Annotated[
        tuple[float, float] | None,
        typer.Option("--near", metavar="X Y", help="Only incidents within --radius of this point on the map."),
    ] = None,
    radius: Annotated[float, typer.Option("--radius", min=0.01, max=1000.0, help="Metres, with --near.")] = 2.0,
    kind: Annotated[
        list[str] | None,
        typer.Option("--kind", help="Only this kind (repeat for more): " + ", ".join(k.value for k in IncidentKind)),
    ] = None,
    since: Annotated[
        str | None, typer.Option("--since", help="Only since: a duration back (30m, 2h, 7d) or a date/time (ISO).")
    ] = None,
    limit: Annotated[int, typer.Option("--limit", min=1, max=1000, help="List at most this many.")] = 100,
    as_json: JsonOpt = False,
) -> None:
    """Safety's memory of incidents: list them, `show` one, `forget` one, `clear` a caution zone.

    With no command, lists the incidents safety remembers, newest first, and the caution zones they
    make; `show` gives one incident with its timeline.

    JSON: {"ok", "incidents": [{id, time, stamp, kind, x, y, reason, ...}], "total", "zones", "store"}.
    Exit 0 listed (also none), 2 bad input, 3 safety unreachable.
    """
    if ctx.invoked_subcommand is not None:
        return
    _list(ctx, list(near) if near is not None else None, radius, kind, since, limit, as_json)


def _one(ctx: typer.Context, incident_id: int, as_json: bool) -> tuple[Incident, IncidentList]:
    try:
        query = IncidentQuery(id=incident_id, limit=1)
        query = msgspec.convert(msgspec.to_builtins(query), IncidentQuery)
    except msgspec.ValidationError as exc:
        _fail(as_json, f"bad incident id {incident_id}: {exc}", EXIT_REFUSED)
    answer = _ask(ctx, query, as_json)
    if not answer.incidents:
        _fail(as_json, f"no incident {incident_id} (forgotten, or never recorded)", EXIT_NOT_FOUND, id=incident_id)
    return answer.incidents[0], answer


def find_recording(incident: Incident, given: Path | None, search: Path) -> Path | None:
    """The recording to show the incident from: --recording, else the file safety noted if it exists
    here, else the same file name under `search` (a copy brought to another computer)."""
    if given is not None:
        return given
    if not incident.recording:
        return None
    noted = Path(incident.recording)
    for candidate in (noted, search / noted.name):
        if candidate.is_file():
            return candidate
    return None


@app.command("show")
def show(
    ctx: typer.Context,
    incident_id: Annotated[int, typer.Argument(metavar="ID", help="The incident's id (`tether incidents`).")],
    recording: Annotated[
        Path | None,
        typer.Option("--recording", help="The MCAP file to take the timeline from (default: the one safety noted)."),
    ] = None,
    window: Annotated[
        float, typer.Option("--window", min=0.5, max=3600.0, help="Seconds of timeline either side.")
    ] = SHOW_WINDOW,
    as_json: JsonOpt = False,
) -> None:
    """Show one incident, with the timeline around it from the recording it is in (as `tether inspect`).

    Exit 0 shown (a recording missing or unreadable is a note, not an error), 2 unknown incident,
    3 safety unreachable.
    """
    incident, _answer = _one(ctx, incident_id, as_json)
    path = find_recording(incident, recording, Path("recordings"))
    rows: list[dict[str, Any]] = []
    note = ""
    if path is None:
        note = (
            f"the recording {incident.recording} is not here; give it with --recording"
            if incident.recording
            else "no recording was known when it happened"
        )
    else:
        rows, note = timeline_rows(path, incident.stamp, window)
    if as_json:
        print(
            json.dumps(
                {
                    "ok": True,
                    "incident": incident_json(incident),
                    "recording": str(path or ""),
                    "note": note,
                    "rows": rows,
                }
            )
        )
        raise typer.Exit(EXIT_OK)
    now = time.time()
    out.print(shown(f"incident {incident.id}: {incident.kind}" + (f" ({incident.source})" if incident.source else "")))
    lines = [
        (
            "when",
            f"{local_time(incident.stamp) or f'stamp {incident.stamp:g} is no date'} ({ago(incident.stamp, now)})",
        ),
        ("where", where(incident) + ("" if incident.yaw is None else f", heading {math.degrees(incident.yaw):.0f}°")),
        (
            "hand",
            "" if incident.hand is None else f"({incident.hand.x:.2f}, {incident.hand.y:.2f}, {incident.hand.z:.2f})",
        ),
        ("rule", incident.rule),
        ("plan", incident.goal_id + (f", step {incident.label or incident.step}" if incident.step is not None else "")),
        ("objects", ", ".join(incident.objects)),
        ("people", ", ".join(incident.people)),
        ("reason", incident.reason),
        ("recording", incident.recording),
        ("cleared", "yes: its caution zone was cleared by an operator" if incident.cleared else ""),
    ]
    for name, value in lines:
        if value:
            out.print(f"  {name + ':':<11}{shown(value)}")
    if note:
        console.print(shown(note), style="yellow")
    for row in rows:
        out.print(f"  {row['dt']:+7.2f} s  {shown(row['kind']):<10} {shown(row['summary'])}")
    raise typer.Exit(EXIT_OK)


def timeline_rows(path: Path, stamp: float, window: float) -> tuple[list[dict[str, Any]], str]:
    """The recording's timeline rows within `window` s of `stamp` (wall clock), each with `dt`, its
    offset from the incident; and a note when the file could not be read or holds no rows then."""
    from services.recorder.reader import RecordingError, read_recording
    from services.recorder.timeline import build_timeline

    try:
        recording = read_recording(path)
    except RecordingError as exc:  # missing, not ours to read (the path is safety's), or not MCAP
        return [], f"the recording cannot be read: {exc}"
    timeline = build_timeline(recording)
    centre = int(stamp * 1e9)
    span = int(window * 1e9)
    rows = []
    for row in timeline.rows:
        if abs(row.log_time - centre) <= span:
            data = row.as_json()
            data["dt"] = round((row.log_time - centre) / 1e9, 3)
            rows.append(data)
    note = "" if rows else f"{path.name} holds nothing within {window:g} s of the incident"
    return rows, note


def _change(
    ctx: typer.Context, incident_id: int, reason: str, action: ForgetAction, token_file: str | None, as_json: bool
) -> NoReturn:
    try:
        token = read_token(token_path(token_file))
    except OSError as exc:
        _fail(as_json, f"cannot read the operator token: {exc}", EXIT_REFUSED)
    try:
        request = ForgetIncident(operator=operator_name(), token=token, id=incident_id, reason=reason, action=action)
        request = msgspec.json.decode(msgspec.json.encode(request), type=ForgetIncident)
    except msgspec.ValidationError as exc:
        _fail(as_json, f"bad request: {exc}", EXIT_REFUSED)
    with command_node(ctx, console) as node:
        try:
            reply: ForgetReply = node.call(keys.FORGET_INCIDENT, request, timeout=CALL_TIMEOUT)
        except CallError as exc:
            _fail(as_json, f"safety unreachable: {exc}", EXIT_UNREACHABLE)
    if as_json:
        print(json.dumps({"ok": reply.ok, "message": reply.message, "changed": reply.changed}))
    elif reply.ok:
        print(printable(reply.message, newlines=True))
    else:
        console.print(shown(f"refused: {reply.message}"))
    raise typer.Exit(EXIT_OK if reply.ok else EXIT_REFUSED)


ReasonOpt = Annotated[str, typer.Option("--reason", help="Why (required); the recording keeps it.")]


@app.command("forget")
def forget(
    ctx: typer.Context,
    incident_id: Annotated[int, typer.Argument(metavar="ID", help="The incident's id (`tether incidents`).")],
    reason: ReasonOpt,
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Forget an incident (operator only: needs the operator token file).

    It no longer warns plans or counts towards a caution zone. Safety records who forgot it and why.

    Exit 0 forgotten, 2 refused (wrong token, unknown incident, no reason), 3 safety unreachable.
    """
    _change(ctx, incident_id, reason, ForgetAction.FORGET, token_file, as_json)


@app.command("clear")
def clear(
    ctx: typer.Context,
    incident_id: Annotated[int, typer.Argument(metavar="ID", help="An incident in the caution zone to clear.")],
    reason: ReasonOpt,
    token_file: TokenFileOpt = None,
    as_json: JsonOpt = False,
) -> None:
    """Clear the caution zone an incident counts towards (operator only: needs the operator token file).

    The robot goes back to its normal limits there; the incidents are kept and still warn plans.

    Exit 0 cleared, 2 refused (wrong token, unknown incident, no reason), 3 safety unreachable.
    """
    _change(ctx, incident_id, reason, ForgetAction.CLEAR, token_file, as_json)
