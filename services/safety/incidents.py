"""Safety's memory of incidents (pure: SQLite from the standard library, no Zenoh).

`IncidentStore` keeps one row per incident in a SQLite file in safety's state directory, and every
incident not forgotten in memory too, with a grid of 1 m cells of where they are: `near`, `query`
and the caution zones are answered from memory and never wait for the file. Two locks: one for the
file (the writer's: `add`, `forget`, `flush`), one for the memory, held only briefly; the writer
takes the file's first, so a reader never waits while SQLite does.

A file that cannot be used (not a database, locked by another process, unwritable) never raises
into safety: the store says what is wrong in `fault`, keeps the incidents it could not write in
memory (at most MAX_PENDING new ones, still counted for zones and warnings) and writes them once
the file is usable again, trying it again at most every RETRY_INTERVAL seconds. A file written by
a newer version is read once, read-only, for the columns this version knows, and never written.
A file replaced while safety runs never takes incidents out of memory: those it lacks are written
into it; only an operator forgets an incident or clears a zone.

The caution zones are computed by the writer's thread (`refresh_zones`), never by a reader: a new
incident (the newest) updates the clustering around it, anything else computes it afresh, and the
new zones (a hazards.ZoneMap, indexed by a grid) are swapped in whole. `forget` computes them too,
before a clear (the zone it clears counts every incident recorded) and after (in force once it
returns). `caution_zones` returns the ones in force without waiting.

`IncidentWatch` decides which of safety's decisions and which reports are incidents; the node
records what it returns.
"""

from __future__ import annotations

import bisect
import contextlib
import heapq
import json
import logging
import math
import sqlite3
import threading
import time
import typing
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from schemas import keys
from schemas.actions import Feedback, GoalStatus
from schemas.common import TEXT_CHARS, Metres, Radians, Vec3
from schemas.executor import ExecutePlanFeedback
from schemas.incidents import (
    MAX_INVOLVED,
    MAX_LISTED,
    MAX_ZONE_KINDS,
    MAX_ZONE_RADIUS,
    REPORTED_KINDS,
    CautionZone,
    ForgetAction,
    Incident,
    IncidentKind,
    IncidentList,
    IncidentQuery,
    IncidentReport,
)
from schemas.safety import ALREADY_LATCHED, Decision, EstopSource, EstopState, Rule
from services.safety.hazards import MIN_CELL, NEAR_LIMIT, NO_ZONES, ZoneMap
from services.safety.monitor import RateLimit, Separation

log = logging.getLogger(__name__)

# The layout this code writes (PRAGMA user_version). A file with a higher one is only ever read.
SCHEMA_VERSION = 1
# How long a statement waits for another process's lock before the store reports it (seconds).
BUSY_TIMEOUT = 0.2
# A file with a fault is tried again at most this often (seconds): not at every incident.
RETRY_INTERVAL = 5.0
# New incidents kept in memory while the file cannot be written; the oldest are dropped beyond this.
MAX_PENDING = 1000
# The index's cell (m).
CELL = 1.0
# Beyond this many cells across, near() looks at every incident instead of cell by cell.
MAX_CELLS = 41
# New incidents remembered for the next update of the zones; beyond this they are computed afresh.
MAX_JOURNAL = 10_000
# Rounds of refresh_zones at most: incidents added while it computed are added in the next round.
ZONE_ROUNDS = 3
# Ids asked for in one statement when a file's incidents are merged into memory.
READ_CHUNK = 500
# The longest texts the schema allows.
MAX_REASON = TEXT_CHARS
MAX_SHORT = 64
MAX_RECORDING = 400
# What the wire allows of a place and a heading (ge, le): a file's value beyond them is not used.
_PLACE = (typing.get_args(Metres)[1].ge, typing.get_args(Metres)[1].le)
_HEADING = (typing.get_args(Radians)[1].ge, typing.get_args(Radians)[1].le)
# The longest list of names (JSON) a file's row is read for: MAX_INVOLVED names, escaped.
MAX_NAMES_JSON = 64 * 1024
# The highest incident number a file's row is read with: the numbers after it still fit SQLite's INTEGER.
MAX_ID = 2**62

_SCHEMA = """
CREATE TABLE IF NOT EXISTS incidents (
    id INTEGER PRIMARY KEY,
    stamp REAL NOT NULL,
    kind TEXT NOT NULL,
    reason TEXT NOT NULL DEFAULT '',
    x REAL, y REAL, yaw REAL,
    hand_x REAL, hand_y REAL, hand_z REAL,
    source TEXT NOT NULL DEFAULT '',
    rule TEXT NOT NULL DEFAULT '',
    goal_id TEXT NOT NULL DEFAULT '',
    step INTEGER,
    label TEXT NOT NULL DEFAULT '',
    objects TEXT NOT NULL DEFAULT '[]',
    people TEXT NOT NULL DEFAULT '[]',
    recording TEXT NOT NULL DEFAULT '',
    cleared INTEGER NOT NULL DEFAULT 0,
    cleared_by TEXT NOT NULL DEFAULT '',
    cleared_reason TEXT NOT NULL DEFAULT '',
    cleared_stamp REAL,
    forgotten INTEGER NOT NULL DEFAULT 0,
    forgotten_by TEXT NOT NULL DEFAULT '',
    forgotten_reason TEXT NOT NULL DEFAULT '',
    forgotten_stamp REAL
);
CREATE INDEX IF NOT EXISTS incidents_xy ON incidents (x, y);
CREATE INDEX IF NOT EXISTS incidents_stamp ON incidents (stamp);
"""
_NAMES = (
    "id",
    "stamp",
    "kind",
    "reason",
    "x",
    "y",
    "yaw",
    "hand_x",
    "hand_y",
    "hand_z",
    "source",
    "rule",
    "goal_id",
    "step",
    "label",
    "objects",
    "people",
    "recording",
    "cleared",
)
_COLUMNS = ", ".join(_NAMES)
_INSERT = f"INSERT INTO incidents ({_COLUMNS}) VALUES ({', '.join('?' * len(_NAMES))})"
# What a column missing from a newer version's file reads as; the first three must be there.
_DEFAULTS = {"reason": "''", "source": "''", "rule": "''", "goal_id": "''", "label": "''", "objects": "'[]'"}
_DEFAULTS |= {"people": "'[]'", "recording": "''", "cleared": "0"}
_REQUIRED = ("id", "stamp", "kind")


class IncidentStoreError(RuntimeError):
    """The file cannot be written now (the message is the store's fault): forgetting waits for it."""


@dataclass(slots=True)
class _Spot:
    """An incident not forgotten that has a position, as the index holds it."""

    id: int
    x: float
    y: float
    stamp: float
    cleared: bool
    kind: IncidentKind

    @property
    def order(self) -> tuple[float, int]:
        return (self.stamp, self.id)


# (id, x, y, stamp, kind): an incident as the clustering sees it.
Point = tuple[int, float, float, float, IncidentKind]


def _cell(x: float, y: float) -> tuple[int, int]:
    return (math.floor(x / CELL), math.floor(y / CELL))


def _short(text: str, limit: int = MAX_SHORT) -> str:
    return text[:limit]


def _names(names: Iterable[str]) -> list[str]:
    return [n[:200] for n in names if n][:MAX_INVOLVED]


def _row(incident: Incident) -> tuple[Any, ...]:
    hand = incident.hand
    return (
        incident.id,
        incident.stamp,
        str(incident.kind),
        incident.reason,
        incident.x,
        incident.y,
        incident.yaw,
        None if hand is None else hand.x,
        None if hand is None else hand.y,
        None if hand is None else hand.z,
        incident.source,
        incident.rule,
        incident.goal_id,
        incident.step,
        incident.label,
        json.dumps(incident.objects),
        json.dumps(incident.people),
        incident.recording,
        int(incident.cleared),
    )


def _listed(text: Any) -> list[str]:
    if isinstance(text, str | bytes) and len(text) > MAX_NAMES_JSON:
        return []
    try:
        value = json.loads(text)
    except (TypeError, ValueError, RecursionError):
        return []
    return _names(str(v) for v in value) if isinstance(value, list) else []


def _number(value: Any, bounds: tuple[float, float]) -> float | None:
    """A REAL column as a finite float within `bounds`; None for NULL or anything else (a newer
    version's file, a hostile one): a value the wire refuses would make every answer listing it
    undecodable."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) and bounds[0] <= number <= bounds[1] else None


def _decoded(raw: bytes) -> str:
    """A TEXT column: one that is not UTF-8 is read with replacement characters, never raises (which
    would leave every incident of the file out of memory)."""
    return raw.decode("utf-8", errors="replace")


def _text(value: Any, limit: int = MAX_SHORT) -> str:
    return value[:limit] if isinstance(value, str) else ""


def _incident(row: Sequence[Any]) -> Incident | None:
    """The incident of a row (the columns of _NAMES), None for one this version cannot read (an
    unknown kind, no time, no number or one beyond MAX_ID)."""
    (id_, stamp, kind, reason, x, y, yaw, hx, hy, hz, source, rule, goal_id, step, label, objects, people) = row[:17]
    if not _numbered(id_):
        return None
    try:
        known = IncidentKind(kind)
        number, when = id_, float(stamp)
    except (TypeError, ValueError):
        return None
    if not math.isfinite(when):
        return None
    hx, hy, hz = _number(hx, _PLACE), _number(hy, _PLACE), _number(hz, _PLACE)
    hand = Vec3(x=hx, y=hy, z=hz) if hx is not None and hy is not None and hz is not None else None
    x, y = _number(x, _PLACE), _number(y, _PLACE)
    return Incident(
        id=number,
        stamp=when,
        kind=known,
        reason=_text(reason, MAX_REASON),
        x=x if y is not None else None,
        y=y if x is not None else None,
        yaw=_number(yaw, _HEADING),
        hand=hand,
        source=_text(source),
        rule=_text(rule),
        goal_id=_text(goal_id),
        step=step if isinstance(step, int) and step >= 0 else None,
        label=_text(label),
        objects=_listed(objects),
        people=_listed(people),
        recording=_text(row[17], MAX_RECORDING),
        cleared=isinstance(row[18], int | float) and row[18] != 0,
    )


def _numbered(id_: Any) -> bool:
    """Whether a file's `id` is an incident number this version reads: an integer from 1 to MAX_ID. A
    text or NULL one (a file not made by this code), or one next to SQLite's largest, is not: it
    stopped safety from starting, or made every incident after it fail to be written."""
    return isinstance(id_, int) and 1 <= id_ <= MAX_ID


# The highest number in a file among those it reads (what _numbered takes).
_TOP = f"SELECT max(id) FROM incidents WHERE typeof(id) = 'integer' AND id BETWEEN 1 AND {MAX_ID}"


def _order(incident: Incident) -> tuple[float, int]:
    return (incident.stamp, incident.id)


def _matches(incident: Incident, q: IncidentQuery) -> bool:
    if q.id is not None and incident.id != q.id:
        return False
    if q.kinds and incident.kind not in q.kinds:
        return False
    if incident.stamp < q.since:
        return False
    if q.x is not None and q.y is not None:
        if incident.x is None or incident.y is None:
            return False
        return math.hypot(incident.x - q.x, incident.y - q.y) <= q.radius
    return True


class IncidentStore:
    """See the module. `version` grows with every change to what near(), query() and the zones
    answer (read without a lock). `clock`: the incidents' time (wall clock); `monotonic`: when to
    try a file with a fault again; `busy_timeout`: how long SQLite waits for another's lock."""

    def __init__(
        self,
        path: Path,
        clock: Callable[[], float] = time.time,
        *,
        busy_timeout: float = BUSY_TIMEOUT,
        monotonic: Callable[[], float] = time.monotonic,
    ) -> None:
        self.path = path
        self._clock = clock
        self._monotonic = monotonic
        self._busy_timeout = busy_timeout
        self.fault = ""
        self.version = 0
        # The writer's: the connection, what waits to be written, the numbering. Taken before `_lock`.
        self._db_lock = threading.RLock()
        self._db: sqlite3.Connection | None = None
        self._retry_at = -math.inf
        # A newer version wrote the file: read once, never written by this process.
        self._disabled = False
        # Incidents not written yet (the file unusable), oldest first; `_keep`: those known before (from
        # a file since replaced), never dropped for room.
        self._pending: dict[int, Incident] = {}
        self._keep: set[int] = set()
        self._renumbered: dict[int, int] = {}
        self._next_id = 1
        # The memory: every incident not forgotten, by id and in (stamp, id) order; where those with a
        # position are. Changed only by a holder of `_db_lock` and `_lock` both; read under `_lock`.
        self._lock = threading.RLock()
        self._incidents: dict[int, Incident] = {}
        self._keys: list[tuple[float, int]] = []
        self._ordered: list[Incident] = []
        self._spots: dict[int, _Spot] = {}
        self._grid: dict[tuple[int, int], list[_Spot]] = {}
        # New incidents since the zones were last updated (None: something else changed, compute afresh).
        self._journal: list[_Spot] | None = None
        # The zones: their clustering (the writer's thread's, under `_zone_lock`) and the map in force.
        self._zone_lock = threading.Lock()
        self._clusters: _Clusters | None = None
        # What refresh_zones was last asked for (count, radius, speed scale): forget computes them too.
        self._zone_params: tuple[int, float, float] | None = None
        self._zones: ZoneMap = NO_ZONES
        with self._db_lock:
            self._connect()

    # The memory (call with both locks held)

    def _put(self, incident: Incident, new: bool = False, ordered: bool = True) -> None:
        """Into memory; `new`: an incident just recorded (the zones may take it without a full update);
        not `ordered`: the caller puts it in (stamp, id) order itself (_put_many)."""
        self._incidents[incident.id] = incident
        if ordered:
            key = _order(incident)
            at = bisect.bisect_left(self._keys, key)
            self._keys.insert(at, key)
            self._ordered.insert(at, incident)
        if incident.x is not None and incident.y is not None:
            spot = _Spot(incident.id, incident.x, incident.y, incident.stamp, incident.cleared, incident.kind)
            self._spots[spot.id] = spot
            cell = self._grid.setdefault(_cell(spot.x, spot.y), [])
            if not cell or cell[-1].order <= spot.order:
                cell.append(spot)
            else:
                bisect.insort(cell, spot, key=lambda s: s.order)
            if new and self._journal is not None and len(self._journal) < MAX_JOURNAL:
                self._journal.append(spot)
            else:
                self._journal = None
        self.version += 1

    def _put_many(self, incidents: list[Incident]) -> None:
        """Many into memory (a file read): oldest first, and the order sorted once, not one by one. A
        number already held is skipped: only a file not made by this code has two rows under one (its
        `id` not the key), and one number held twice would list an incident after it is forgotten."""
        unique: dict[int, Incident] = {}
        for incident in incidents:
            if incident.id not in self._incidents:
                unique.setdefault(incident.id, incident)
        if len(unique) < len(incidents):
            log.error(
                "incident store %s: %d rows skipped: their incident numbers repeat another row's",
                self.path,
                len(incidents) - len(unique),
            )
        incidents = sorted(unique.values(), key=_order)
        for incident in incidents:
            self._put(incident, ordered=False)
        self._ordered = sorted(self._ordered + incidents, key=_order)
        self._keys = [_order(i) for i in self._ordered]

    def _drop(self, incident_id: int) -> Incident | None:
        incident = self._incidents.pop(incident_id, None)
        if incident is None:
            return None
        at = bisect.bisect_left(self._keys, _order(incident))
        del self._keys[at]
        del self._ordered[at]
        spot = self._spots.pop(incident_id, None)
        if spot is not None:
            cell = self._grid.get(_cell(spot.x, spot.y), [])
            cell.remove(spot)
            if not cell:
                self._grid.pop(_cell(spot.x, spot.y), None)
        self._journal = None
        self.version += 1
        return incident

    def _mark_cleared(self, incident_id: int) -> None:
        incident = self._incidents.get(incident_id)
        if incident is None or incident.cleared:
            return
        incident = msgspec.structs.replace(incident, cleared=True)
        self._incidents[incident_id] = incident
        self._ordered[bisect.bisect_left(self._keys, _order(incident))] = incident
        if (spot := self._spots.get(incident_id)) is not None:
            spot.cleared = True
        self._journal = None
        self.version += 1

    # The file (the writer's: call with `_db_lock` held)

    def _fail(self, what: str, exc: BaseException) -> None:
        """Record a fault and let the connection go: it is opened again after RETRY_INTERVAL."""
        fault = f"incident store {self.path}: {what}: {exc}"
        if fault != self.fault:
            log.error("%s; incidents are kept in memory (%d) until it can be written", fault, len(self._pending))
        self.fault = fault
        self._retry_at = self._monotonic() + RETRY_INTERVAL
        if self._db is not None:
            with contextlib.suppress(sqlite3.Error):
                self._db.close()
            self._db = None

    def _connect(self) -> sqlite3.Connection | None:
        """The open file, opening (and creating) it if it is not and it is time to try; None while it
        cannot be used. Opening merges its incidents into memory (see _merge)."""
        if self._db is not None:
            return self._db
        if self._disabled or self._monotonic() < self._retry_at:
            return None
        db: sqlite3.Connection | None = None
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            db = sqlite3.connect(self.path, timeout=self._busy_timeout, check_same_thread=False, isolation_level=None)
            db.text_factory = _decoded
            version = int(db.execute("PRAGMA user_version").fetchone()[0])
            if version > SCHEMA_VERSION:
                db.close()
                db = None
                self._read_newer(version)
                return None
            if version < SCHEMA_VERSION:
                db.executescript(f"BEGIN IMMEDIATE;{_SCHEMA}PRAGMA user_version = {SCHEMA_VERSION};COMMIT;")
            self._merge(db)
        except (sqlite3.Error, OSError) as exc:
            if db is not None:
                with contextlib.suppress(sqlite3.Error):
                    db.close()
            self._fail("cannot be opened", exc)
            return None
        self._db = db
        return db

    def _usable(self) -> None:
        """The file is open and nothing waits in memory any more: no fault. Only `_flush` says so, once
        what waited is written: a store that says it has no fault has what it kept in the file."""
        if self.fault:
            log.warning("incident store %s is usable again", self.path)
        self.fault = ""

    def _read_newer(self, version: int) -> None:
        """A file of a newer version: its incidents (the columns this version knows) into memory, read
        through a read-only connection; never opened for writing again."""
        fault = (
            f"incident store {self.path} was written by a newer version of tether (schema {version}; this one "
            f"knows up to {SCHEMA_VERSION}): read only, never written; new incidents are kept in memory only"
        )
        try:
            ro = sqlite3.connect(
                f"{self.path.resolve().as_uri()}?mode=ro", uri=True, timeout=self._busy_timeout, check_same_thread=False
            )
            ro.text_factory = _decoded
            try:
                columns = {r[1] for r in ro.execute("PRAGMA table_info(incidents)").fetchall()}
                rows: list[Any] = []
                if all(c in columns for c in _REQUIRED):
                    chosen = ", ".join(n if n in columns else _DEFAULTS.get(n, "NULL") for n in _NAMES)
                    live = " WHERE coalesce(forgotten, 0) = 0" if "forgotten" in columns else ""
                    rows = ro.execute(f"SELECT {chosen} FROM incidents{live}").fetchall()
            finally:
                ro.close()
        except sqlite3.Error as exc:
            self._fail(f"written by a newer version of tether (schema {version}) and cannot be read", exc)
            return
        self._disabled = True
        read = [i for r in rows if (i := _incident(r)) is not None]
        with self._lock:
            self._put_many([i for i in read if i.id not in self._incidents])
        self._next_id = max(self._next_id, max((i.id for i in read), default=0) + 1)
        self.fault = f"{fault} ({len(read)} of its incidents read)"
        log.error("%s", self.fault)

    def _merge(self, db: sqlite3.Connection) -> None:
        """The file's incidents into memory, those in memory it lacks to be written into it (an incident
        held under a number the file gives another is renumbered): a file replaced while safety runs
        never takes an incident out of memory. Raises sqlite3.Error."""
        ident = {
            r[0]: (r[1], r[2], r[3])
            for r in db.execute("SELECT id, stamp, kind, forgotten FROM incidents")
            if _numbered(r[0])
        }
        top = max(max(ident, default=0), self._next_id - 1)
        # Memory is only changed by this thread (`_db_lock`): read here without `_lock`.
        renumber: list[Incident] = []
        for incident in self._incidents.values():
            there = ident.get(incident.id)
            if there is None:
                if incident.id not in self._pending:
                    self._pending[incident.id] = incident
                    self._keep.add(incident.id)
            elif there[:2] != (incident.stamp, str(incident.kind)):
                renumber.append(incident)
        moving = {i.id for i in renumber}
        wanted = [i for i, (_, _, gone) in ident.items() if not gone and (i not in self._incidents or i in moving)]
        if not self._incidents:  # the first time: everything
            rows = db.execute(f"SELECT {_COLUMNS} FROM incidents WHERE forgotten = 0").fetchall()
        else:
            rows = []
            for at in range(0, len(wanted), READ_CHUNK):
                chunk = wanted[at : at + READ_CHUNK]
                rows += db.execute(
                    f"SELECT {_COLUMNS} FROM incidents WHERE id IN ({', '.join('?' * len(chunk))})", chunk
                ).fetchall()
        read = [i for r in rows if (i := _incident(r)) is not None]
        if not renumber and not read:
            self._next_id = top + 1
            return
        with self._lock:
            for incident in renumber:
                top += 1
                log.warning(
                    "incident %d is held as %d: the incident store %s has another under its number",
                    incident.id,
                    top,
                    self.path,
                )
                self._drop(incident.id)
                moved = msgspec.structs.replace(incident, id=top)
                self._put(moved)
                known = incident.id in self._keep or incident.id not in self._pending
                self._pending.pop(incident.id, None)
                self._keep.discard(incident.id)
                self._pending[top] = moved
                if known:
                    self._keep.add(top)
                self._renumbered[incident.id] = top
            self._put_many(read)
        self._next_id = top + 1

    @property
    def size(self) -> int:
        """How many incidents (not forgotten) the memory holds."""
        return len(self._incidents)

    @property
    def pending(self) -> int:
        """How many incidents wait in memory to be written."""
        return len(self._pending)

    def close(self) -> None:
        with self._db_lock:
            if self._db is not None:
                with contextlib.suppress(sqlite3.Error):
                    self._db.close()
                self._db = None

    def flush(self) -> bool:
        """Write what waits in memory (if it is time to try the file); whether everything is written.
        The writer's thread calls it when idle, so incidents kept while the file was locked are written
        soon after it is released, not only with the next incident."""
        with self._db_lock:
            return self._flush()

    def _flush(self) -> bool:
        """See flush; call with `_db_lock` held. An incident whose number is taken meanwhile is written
        under the next free one (`_renumbered` says which)."""
        db = self._connect()
        if db is None:
            self._trim()
            return False
        if not self._pending:
            self._usable()
            return True
        try:
            db.execute("BEGIN IMMEDIATE")
            try:
                marks = ", ".join("?" * len(self._pending))
                taken = {
                    r[0] for r in db.execute(f"SELECT id FROM incidents WHERE id IN ({marks})", list(self._pending))
                }
                top = max(int(db.execute(_TOP).fetchone()[0] or 0), self._next_id - 1)
                written: list[Incident] = []
                for incident in self._pending.values():
                    if incident.id in taken:
                        top += 1
                        incident = msgspec.structs.replace(incident, id=top)
                    written.append(incident)
                db.executemany(_INSERT, [_row(i) for i in written])
                db.execute("COMMIT")
            except BaseException:
                if db.in_transaction:
                    db.execute("ROLLBACK")
                raise
        except sqlite3.Error as exc:
            self._fail("cannot be written", exc)
            self._trim()
            return False
        moved = [(old, i) for old, i in zip(list(self._pending), written, strict=True) if old != i.id]
        if moved:
            with self._lock:
                for old, incident in moved:
                    log.warning("incident %d kept in memory is written as %d (its number was taken)", old, incident.id)
                    self._drop(old)
                    self._put(incident)
                    self._renumbered[old] = incident.id
        self._next_id = max(self._next_id, top + 1)
        self._pending.clear()
        self._keep.clear()
        self._usable()
        return True

    def _trim(self) -> None:
        """Drop the oldest new incidents waiting beyond MAX_PENDING (those known before are kept)."""
        extra = len(self._pending) - len(self._keep) - MAX_PENDING
        if extra <= 0:
            return
        dropped = [i for i in self._pending if i not in self._keep][:extra]
        log.error("%d incidents are dropped: %d new ones wait in memory already", len(dropped), MAX_PENDING)
        with self._lock:
            for incident_id in dropped:
                del self._pending[incident_id]
                self._drop(incident_id)

    # Writing

    def add(
        self,
        kind: IncidentKind,
        reason: str,
        *,
        x: float | None = None,
        y: float | None = None,
        yaw: float | None = None,
        hand: Vec3 | None = None,
        source: str = "",
        rule: str = "",
        goal_id: str = "",
        step: int | None = None,
        label: str = "",
        objects: Sequence[str] = (),
        people: Sequence[str] = (),
        recording: str = "",
    ) -> Incident:
        """Record an incident: in memory at once (near, query and the next zone update see it), then
        into the file if it can be written; it is returned with its id either way. For one writer
        thread (safety's recording thread): it may wait on the file, readers never do."""
        with self._db_lock:
            incident = Incident(
                id=self._next_id,
                stamp=self._clock(),
                kind=kind,
                reason=reason[:MAX_REASON],
                x=x,
                y=y,
                yaw=yaw,
                hand=hand,
                source=_short(source),
                rule=_short(rule),
                goal_id=_short(goal_id),
                step=step if step is None or step >= 0 else None,
                label=_short(label),
                objects=_names(objects),
                people=_names(people),
                recording=recording[:MAX_RECORDING],
            )
            self._next_id += 1
            self._pending[incident.id] = incident
            with self._lock:
                self._put(incident, new=True)
            self._renumbered.clear()
            self._flush()
            if (new_id := self._renumbered.get(incident.id)) is not None:
                return msgspec.structs.replace(incident, id=new_id)
            return incident

    def forget(self, incident_id: int, action: ForgetAction, operator: str, reason: str, radius: float) -> list[int]:
        """FORGET: that incident no longer warns or counts. CLEAR: every incident not cleared within
        `radius` of its position, and those of the caution zone it is in, no longer count towards a
        zone (they still warn). The zones are computed again (as refresh_zones was last asked) before a
        clear and after either. Returns the ids changed; KeyError for an unknown or forgotten id;
        IncidentStoreError while the file cannot be written (it is tried now, whenever it failed)."""
        with self._db_lock:
            self._retry_at = -math.inf  # the operator asks: try the file now
            if not self._flush():
                raise IncidentStoreError(self.fault or f"incident store {self.path} cannot be written")
            db = self._db
            assert db is not None
            try:
                row = db.execute(
                    "SELECT x, y, forgotten, cleared FROM incidents WHERE id = ?", (incident_id,)
                ).fetchone()
            except sqlite3.Error as exc:
                self._fail("cannot be read", exc)
                raise IncidentStoreError(self.fault) from None
            if row is None:
                raise KeyError(f"no incident {incident_id}")
            x, y, forgotten, cleared = row
            if forgotten:
                raise KeyError(f"incident {incident_id} is already forgotten")
            now = self._clock()
            if action is ForgetAction.FORGET:
                ids = [incident_id]
                sql = "UPDATE incidents SET forgotten = 1, forgotten_by = ?, forgotten_reason = ?, forgotten_stamp = ?"
            else:
                ids = [] if cleared else [incident_id]
                if x is not None and y is not None:
                    with self._lock:
                        ids += [s.id for s in self._within([(x, y)], radius) if not s.cleared]
                    # The zone with every incident recorded so far: the writer adds one, then computes the
                    # zones; a clear in between missed the new ones, which made the zone again at once.
                    self._rezone()
                    ids += self._zone_mates(incident_id)
                ids = sorted(set(ids))
                sql = "UPDATE incidents SET cleared = 1, cleared_by = ?, cleared_reason = ?, cleared_stamp = ?"
            if not ids:
                return []
            try:
                db.execute("BEGIN IMMEDIATE")
                db.executemany(f"{sql} WHERE id = ?", [(operator[:200], reason[:MAX_REASON], now, i) for i in ids])
                db.execute("COMMIT")
            except sqlite3.Error as exc:
                if db.in_transaction:
                    with contextlib.suppress(sqlite3.Error):
                        db.execute("ROLLBACK")
                self._fail("cannot be written", exc)
                raise IncidentStoreError(self.fault) from None
            with self._lock:
                for i in ids:
                    if action is ForgetAction.FORGET:
                        self._drop(i)
                    else:
                        self._mark_cleared(i)
            # In force before the operator hears it is done: a query or the gate right after still
            # found the zone until the writer's thread came round to it.
            self._rezone()
            return ids

    def _rezone(self) -> None:
        """The zones computed again as last asked for (none asked yet: nothing to compute)."""
        if (params := self._zone_params) is None:
            return
        try:
            self.refresh_zones(*params)
        except Exception:  # what is forgotten or cleared stays so: the writer's thread computes them next
            log.exception("the caution zones could not be computed; those computed last stay in force")

    def _zone_mates(self, incident_id: int) -> list[int]:
        """The incidents not cleared of the caution zone `incident_id` is in (none: not in one)."""
        with self._zone_lock:
            clusters = self._clusters
            if clusters is None or (seed := clusters.seat.get(incident_id)) is None:
                return []
            members = [p[0] for p in clusters.members[seed]]
        with self._lock:
            return [i for i in members if i in self._spots and not self._spots[i].cleared]

    # Reading: from memory, never waiting for the file

    def query(self, q: IncidentQuery) -> IncidentList:
        """The incidents `q` asks for, newest first, with how many matched, the caution zones in force
        and the store's fault. From memory: the lock is held only to take the candidates."""
        with self._lock:
            fault, zones = self.fault, self._zones
            if q.id is not None:
                found = self._incidents.get(q.id)
                candidates = [found] if found is not None else []
            elif q.x is not None and q.y is not None and (cells := self._cells_near(q.x, q.y, q.radius)) is not None:
                candidates = sorted((self._incidents[s.id] for c in cells for s in self._grid.get(c, ())), key=_order)
            else:
                candidates = self._ordered[bisect.bisect_left(self._keys, (q.since,)) :]
        matched = [i for i in reversed(candidates) if _matches(i, q)]
        return IncidentList(
            incidents=matched[: q.limit], total=len(matched), zones=list(zones.zones[:MAX_LISTED]), store=fault
        )

    def _cells_near(self, x: float, y: float, radius: float) -> list[tuple[int, int]] | None:
        """The index's cells within `radius` of (x, y); None when there are more of them than filled cells."""
        span = math.ceil(radius / CELL)
        if (2 * span + 1) ** 2 > len(self._grid):
            return None
        cx, cy = _cell(x, y)
        return [(i, j) for i in range(cx - span, cx + span + 1) for j in range(cy - span, cy + span + 1)]

    def _within(self, points: Sequence[tuple[float, float]], radius: float) -> Iterator[_Spot]:
        """The indexed incidents within `radius` of any point, newest first (consume with `_lock` held)."""
        if not points:
            return iter(())
        span = math.ceil(radius / CELL)
        cells: dict[tuple[int, int], bool] = {}  # cell -> wholly inside a circle
        if 2 * span + 1 > MAX_CELLS:
            cells = dict.fromkeys(self._grid, False)
        else:
            for px, py in points:
                cx, cy = _cell(px, py)
                for i in range(cx - span, cx + span + 1):
                    for j in range(cy - span, cy + span + 1):
                        if (i, j) not in self._grid or cells.get((i, j)):
                            continue
                        corners = ((i * CELL, j * CELL), ((i + 1) * CELL, (j + 1) * CELL))
                        far = (
                            max(abs(corners[0][0] - px), abs(corners[1][0] - px)),
                            max(abs(corners[0][1] - py), abs(corners[1][1] - py)),
                        )
                        cells[(i, j)] = math.hypot(*far) <= radius
        lists = [(reversed(self._grid[c]), inside) for c, inside in cells.items()]
        merged = heapq.merge(
            *(((s, inside) for s in spots) for spots, inside in lists), key=lambda p: p[0].order, reverse=True
        )

        def near(s: _Spot) -> bool:
            return any(math.hypot(s.x - px, s.y - py) <= radius for px, py in points)

        return (s for s, inside in merged if inside or near(s))

    def near(self, points: Sequence[tuple[float, float]], radius: float, limit: int = NEAR_LIMIT) -> list[Incident]:
        """The incidents (not forgotten) within `radius` of any of `points`, newest first, each once.
        From memory (whatever the file's state)."""
        with self._lock:
            found: list[Incident] = []
            for spot in self._within(points, radius):
                found.append(self._incidents[spot.id])
                if len(found) >= limit:
                    break
            return found

    # The caution zones

    def caution_zones(self) -> ZoneMap:
        """The caution zones in force, as refresh_zones last computed them (none before): never waits."""
        return self._zones

    def refresh_zones(self, count: int, radius: float, speed_scale: float) -> ZoneMap:
        """Places with at least `count` incidents (with a position, not forgotten, not cleared) within
        `radius` of one of them, oldest first: clustered greedily from the oldest incident on, each
        taking those within `radius` of it not yet in a zone. A zone is centred on its incidents and
        reaches the farthest (at least `radius`). For the writer's thread, after a change: new
        incidents update the clustering around them (_Clusters.add), anything else computes it afresh
        outside the memory's lock; the new zones are then swapped in (`version` grows)."""
        params = (count, radius, speed_scale)
        with self._zone_lock:
            self._zone_params = params
            # Incidents added while the zones were computed are added after, in another round.
            for _ in range(ZONE_ROUNDS):
                nearby: list[tuple[_Spot, list[list[_Spot]]]] = []
                points: list[Point] | None = None
                with self._lock:
                    clusters, journal = self._clusters, self._journal
                    if clusters is not None and clusters.params == params and journal is not None:
                        if not journal:
                            return self._zones
                        # An update looks at every incident around each new one: where most of them are
                        # (a flood of reports at one place) that costs more than computing afresh, once
                        # for each new incident, and the writer would fall ever further behind.
                        crowd = sum(len(c) for spot in journal for c in self._cells_at(spot.x, spot.y, radius))
                        if crowd <= len(self._spots):
                            nearby = [(spot, self._cells_around(spot.x, spot.y, radius)) for spot in journal]
                    if not nearby:
                        points = [(s.id, s.x, s.y, s.stamp, s.kind) for s in self._spots.values() if not s.cleared]
                    self._journal = []
                if points is not None:
                    clusters = self._clusters = _cluster(points, params)
                elif clusters is None or not _update(clusters, nearby, radius):
                    self._clusters = None  # a new zone changes those after it: computed afresh next round
                    continue
                if clusters.map is not self._zones:
                    with self._lock:
                        self._zones = clusters.map
                        self.version += 1
            return self._zones

    def _cells_at(self, x: float, y: float, radius: float) -> Iterator[list[_Spot]]:
        """The index's cells within `radius` of (x, y) that hold incidents (call with `_lock` held)."""
        span = math.ceil(radius / CELL)
        cx, cy = _cell(x, y)
        cells = ((i, j) for i in range(cx - span, cx + span + 1) for j in range(cy - span, cy + span + 1))
        return (spots for c in cells if (spots := self._grid.get(c)))

    def _cells_around(self, x: float, y: float, radius: float) -> list[list[_Spot]]:
        """Copies of the index's cells within `radius` of (x, y) (call with `_lock` held)."""
        return [list(spots) for spots in self._cells_at(x, y, radius)]


def _update(clusters: _Clusters, nearby: list[tuple[_Spot, list[list[_Spot]]]], radius: float) -> bool:
    """Add new incidents (each with copies of the index's cells around it) to the clustering; False
    when one changes more than its own zone (compute afresh). The distance is measured exactly as
    _cluster measures it, so both give the same zones."""
    for spot, cells in nearby:
        reach = [
            (s.id, s.x, s.y, s.stamp, s.kind)
            for cell in cells
            for s in cell
            if s.order < spot.order and not s.cleared and math.hypot(s.x - spot.x, s.y - spot.y) <= radius
        ]
        if not clusters.add((spot.id, spot.x, spot.y, spot.stamp, spot.kind), reach):
            return False
    return True


def _zone(members: list[Point], radius: float, speed_scale: float) -> CautionZone:
    """The zone of `members` (in the order of their time, so the same members give the same zone)."""
    members = sorted(members, key=lambda s: (s[3], s[0]))
    x = sum(s[1] for s in members) / len(members)
    y = sum(s[2] for s in members) / len(members)
    reach = max(math.hypot(s[1] - x, s[2] - y) for s in members)
    return CautionZone(
        x=x,
        y=y,
        radius=min(MAX_ZONE_RADIUS, max(radius, reach)),
        count=len(members),
        speed_scale=speed_scale,
        incidents=sorted(s[0] for s in members)[:MAX_LISTED],
        last=max(s[3] for s in members),
        kinds=[k for k, _ in Counter(s[4] for s in members).most_common(MAX_ZONE_KINDS)],
    )


@dataclass
class _Clusters:
    """The greedy clustering of IncidentStore.refresh_zones, kept so that a new incident updates it:
    `members` of each zone by its seed (the zone's oldest incident; in the zones' order), `position`
    of each seed's zone in `map`, `seat`: the seed whose zone took each incident, `free`: for each
    incident that made no zone at its turn (not taken by an older one), how many it had within reach
    then; `newest`: the latest (stamp, id) clustered."""

    params: tuple[int, float, float]
    members: dict[int, list[Point]]
    position: dict[int, int]
    seat: dict[int, int]
    free: dict[int, int]
    newest: tuple[float, int]
    map: ZoneMap

    def add(self, p: Point, reach: list[Point]) -> bool:
        """`p`, newer than all clustered, with the incidents (not cleared) within reach of it. Clustered
        afresh, the older seeds within reach would see it in turn: the first zone's seed takes it; a
        seed before that which made no zone counts one more (if that makes its zone, later zones
        change: False, compute afresh); taken by none, it is the last seed, with those within reach
        that no zone took. Exactly what _cluster gives."""
        count, radius, scale = self.params
        if (p[3], p[0]) <= self.newest:
            return False
        seeds = sorted((s for s in reach if s[0] in self.members or s[0] in self.free), key=lambda s: (s[3], s[0]))
        counted: list[int] = []
        taker: int | None = None
        for s in seeds:
            if s[0] in self.members:
                taker = s[0]
                break
            if self.free[s[0]] + 1 >= count:
                return False
            counted.append(s[0])
        for seed in counted:
            self.free[seed] += 1
        self.newest = (p[3], p[0])
        if taker is not None:
            self.members[taker].append(p)
            self.seat[p[0]] = taker
            self.map = self.map.with_zone(self.position[taker], _zone(self.members[taker], radius, scale))
            return True
        free = [s for s in reach if s[0] not in self.seat] + [p]
        if len(free) < count:
            self.free[p[0]] = len(free)
            return True
        self.members[p[0]] = free
        self.position[p[0]] = len(self.map)
        for s in free:
            self.seat[s[0]] = p[0]
        self.map = self.map.with_zone(len(self.map), _zone(free, radius, scale))
        return True


def _cluster(points: list[Point], params: tuple[int, float, float]) -> _Clusters:
    """See IncidentStore.refresh_zones; `points`: (id, x, y, stamp, kind)."""
    count, radius, speed_scale = params
    points.sort(key=lambda s: (s[3], s[0]))
    size = max(radius, MIN_CELL)

    def cell(s: Point) -> tuple[int, int]:
        return (math.floor(s[1] / size), math.floor(s[2] / size))

    grid: dict[tuple[int, int], dict[int, Point]] = {}
    for s in points:
        grid.setdefault(cell(s), {})[s[0]] = s
    members: dict[int, list[Point]] = {}
    seat: dict[int, int] = {}
    free: dict[int, int] = {}
    for seed in points:
        if seed[0] in seat:
            continue
        cx, cy = cell(seed)
        near = [
            s
            for i in (cx - 1, cx, cx + 1)
            for j in (cy - 1, cy, cy + 1)
            for s in grid.get((i, j), {}).values()
            if math.hypot(s[1] - seed[1], s[2] - seed[2]) <= radius
        ]
        if len(near) < count:
            free[seed[0]] = len(near)
            continue
        for s in near:
            seat[s[0]] = seed[0]
            del grid[cell(s)][s[0]]
        members[seed[0]] = near
    zones = [_zone(m, radius, speed_scale) for m in members.values()]
    newest = (points[-1][3], points[-1][0]) if points else (-math.inf, 0)
    position = {seed: i for i, seed in enumerate(members)}
    return _Clusters(params, members, position, seat, free, newest, ZoneMap.of(zones, radius))


# Which decisions are incidents


@dataclass(frozen=True)
class Draft:
    """An incident as safety notices it, before the node adds where the robot was and records it.
    `x`, `y`: where it happened when a reporter knows better than the robot's pose."""

    kind: IncidentKind
    reason: str
    source: str = ""
    rule: str = ""
    objects: tuple[str, ...] = ()
    people: tuple[str, ...] = ()
    x: float | None = None
    y: float | None = None
    goal_id: str = ""
    step: int | None = None
    label: str = ""


# Vetoes of one rule on one key while a plan runs within this many seconds are one incident.
VETO_WINDOW = 5.0
# Reports taken: up to REPORT_BURST at once, then one every REPORT_PERIOD seconds on average; more are
# dropped with a warning. A robot sees a few such things an hour; 20 a second, kept, grew safety's
# memory and file by about 100 KB a second for as long as a reporter looped.
REPORT_BURST = 20
REPORT_PERIOD = 10.0
# Who reports each kind (README): each reporter's reports come out of a budget of its own, REPORT_BURST
# at once then one every REPORT_PERIOD s. With one budget for all, an executor looping on grasp_failed
# used it up and the robot's collisions and drops were dropped.
REPORTER = {IncidentKind.GRASP_FAILED: "executor", IncidentKind.DROPPED: "robot", IncidentKind.COLLISION: "robot"}
# A pause counts as a near-miss while a plan runs or the base moved this recently (seconds).
MOVED_RECENTLY = 2.0
# Refusals that say nothing about a place: the e-stop (its own incident), the control mode, a missing
# approval and the command rate (the operator's and the clock's doing).
# Refusals that say nothing of a place: not hazards to remember (one_motion: two motions asked at once).
_NOT_HAZARDS = frozenset({Rule.ESTOP, Rule.MODE, Rule.APPROVAL, Rule.COMMAND_RATE, Rule.ONE_MOTION})
_ESTOP_KINDS = {EstopSource.MONITOR.value: IncidentKind.MONITOR, EstopSource.WATCHDOG.value: IncidentKind.WATCHDOG}


@dataclass
class IncidentWatch:
    """Which of safety's decisions are incidents, pure (`clock`: monotonic seconds). Knows which plan
    runs (the executor's plan/execute status and feedback) and whether the base moved lately."""

    near_miss_distance: float
    clock: Callable[[], float] = time.monotonic
    _plan: str = ""
    _step: int | None = None
    _label: str = ""
    _vetoes: dict[tuple[str, str], float] = field(default_factory=dict)
    _moved: float = -math.inf
    _paused_noted: bool = False
    _reports: dict[str, RateLimit] = field(
        default_factory=lambda: {
            who: RateLimit(1.0 / REPORT_PERIOD, REPORT_BURST * REPORT_PERIOD) for who in set(REPORTER.values())
        }
    )
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def plan_status(self, status: GoalStatus) -> None:
        with self._lock:
            if not status.state.terminal:
                if status.goal_id != self._plan:
                    self._plan, self._step, self._label = status.goal_id, None, ""
            elif status.goal_id == self._plan:
                self._plan, self._step, self._label = "", None, ""

    def plan_feedback(self, feedback: Feedback[ExecutePlanFeedback]) -> None:
        with self._lock:
            if feedback.goal_id != self._plan:
                self._plan = feedback.goal_id
            if feedback.feedback.step is not None:
                self._step = feedback.feedback.step
                self._label = feedback.feedback.label or str(feedback.feedback.step + 1)

    def context(self) -> tuple[str, int | None, str]:
        """The plan running (goal id, "" for none), its step and the step's label."""
        with self._lock:
            return self._plan, self._step, self._label

    def base_moved(self, moving: bool) -> None:
        if moving:
            with self._lock:
                self._moved = self.clock()

    def decided(self, events: Iterable[Any], latch: EstopState) -> list[Draft]:
        """The incidents in a ruling's events (services.safety.gate.GateEvent): the e-stop latching
        (kind by who latched it; not one asked for while it held), and a veto of a program's motion
        command (cmd/* goals, cmd/cmd_vel) while a plan runs, one per rule and key within VETO_WINDOW
        (not for the e-stop, which is its own incident, nor the mode, a missing approval or the rate)."""
        drafts: list[Draft] = []
        for event in events:
            rule = str(event.rule) if event.rule is not None else ""
            if event.decision is Decision.LATCHED and event.key == keys.ESTOP.path:
                if ALREADY_LATCHED in event.values:
                    continue  # the latch that holds is the incident; this one only asked for it again
                source = latch.source if latch.latched else ""
                kind = _ESTOP_KINDS.get(source, IncidentKind.ESTOP)
                drafts.append(Draft(kind, event.reason, source=source, rule=rule))
            elif (
                event.decision is Decision.VETOED
                and (event.key == keys.CMD_VEL.path or (event.key.startswith("cmd/") and "/_action/" in event.key))
                and event.rule is not None
                and event.rule not in _NOT_HAZARDS
                and "count" not in event.values
            ):
                now = self.clock()
                with self._lock:
                    if not self._plan:
                        continue
                    last = self._vetoes.get((event.key, rule))
                    self._vetoes = {k: v for k, v in self._vetoes.items() if now - v < VETO_WINDOW}
                    if last is not None and now - last < VETO_WINDOW:
                        continue
                    self._vetoes[(event.key, rule)] = now
                drafts.append(Draft(IncidentKind.VETO, event.reason, source=event.key, rule=rule))
        return drafts

    def separation(self, sep: Separation) -> Draft | None:
        """A pause for a person nearer than `near_miss_distance` while the robot was under way: one
        near-miss per pause."""
        with self._lock:
            if sep.scale > 0.0:
                self._paused_noted = False
                return None
            if self._paused_noted or sep.distance is None or sep.distance >= self.near_miss_distance:
                return None
            if not self._plan and self.clock() - self._moved > MOVED_RECENTLY:
                return None
            self._paused_noted = True
        people = (sep.person,) if sep.person else ()
        why = f"paused for a person {sep.distance:.2f} m away (near-miss within {self.near_miss_distance:g} m)"
        if sep.reason:
            why = f"{why}: {sep.reason}"
        return Draft(IncidentKind.NEAR_MISS, why, source="safety", rule=str(Rule.HUMAN_SEPARATION), people=people)

    def report(self, report: IncidentReport, source: str = "") -> Draft | str:
        """A report from the executor or the sim: its draft, or why it is not taken."""
        if report.kind not in REPORTED_KINDS:
            allowed = ", ".join(sorted(str(k) for k in REPORTED_KINDS))
            return f"incident report of kind {report.kind} ignored: only {allowed} may be reported"
        who = REPORTER[report.kind]
        if not self._reports[who].allow(self.clock()):
            kinds = ", ".join(str(kind) for kind, by in REPORTER.items() if by == who)
            return (
                f"incident report ({report.kind}) dropped: the {who}'s reports ({kinds}) came more than "
                f"{REPORT_BURST} at once, or more than one every {REPORT_PERIOD:g} s on average"
            )
        goal_id, step, label = self.context()
        return Draft(
            report.kind,
            report.reason,
            source=source,
            objects=tuple(report.objects),
            people=tuple(report.people),
            x=report.x,
            y=report.y,
            goal_id=report.goal_id or goal_id,
            step=report.step if report.step is not None else (step if not report.goal_id else None),
            label=report.label or (label if not report.goal_id else ""),
        )


def seed(path: Path, incidents: Iterable[Incident]) -> int:
    """Write `incidents` (their ids as given, none taken yet) into the store at `path` in one
    transaction, creating it if need be: for benchmarks and tests of a store that has seen a lot. Not
    for safety, which adds one at a time; raises sqlite3.Error. Returns how many were written."""
    IncidentStore(path).close()  # the schema and its version, as safety makes them
    db = sqlite3.connect(path)
    try:
        with db:
            rows = [_row(i) for i in incidents]
            db.executemany(_INSERT, rows)
    finally:
        db.close()
    return len(rows)
