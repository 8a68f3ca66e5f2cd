"""A recording drawn from above as a PNG (matplotlib's Agg canvas: no display): the world and what happened in it."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from shapely.geometry import Point, Polygon

from schemas import keys
from schemas.robot import Odometry
from schemas.safety import Decision
from schemas.world import KeepOut, PerceivedHumans, World
from services.recorder.reader import RecordingFile
from services.recorder.timeline import Row, Undecodable, decode
from services.worldmodel import WorldModel, wall_shape

if TYPE_CHECKING:  # matplotlib is imported when a map is drawn: the CLI starts without it
    from matplotlib.axes import Axes
    from matplotlib.patches import Polygon as PolygonPatch

# Positions closer than this are one point on the map (metres): a person standing still, two vetoes
# of the same goal.
SAME_SPOT = 0.05
MARGIN = 0.5
# Labels sit this far inside the room or zone they name (metres).
LABEL_INSET = 0.15
# Inches: the map's width; its height follows the world's shape within these bounds.
WIDTH = 12.0
HEIGHT_RANGE = (4.0, 12.0)
DPI = 100
# Times listed in one marker's label before the rest are counted.
LABEL_TIMES = 3
# Marks of one kind, and people, named on the map at most: more labels only cover the map, and each
# takes matplotlib milliseconds (a file of thousands of vetoes at distinct spots took minutes). The
# rest are drawn unnamed, the legend says how many.
MAX_LABELS = 100
ROOM_COLOURS = ("#e8f1fa", "#eef7e6", "#fbf3e4", "#f3eafa", "#e9f6f5", "#faeaea", "#f4f4e2")


@dataclass
class Track:
    """What the robot and the people did: the odometry path and each person's distinct positions."""

    path: list[tuple[float, float]] = field(default_factory=list)
    people: dict[str, list[tuple[float, float]]] = field(default_factory=dict)


@dataclass(frozen=True)
class Mark:
    """A point on the map with its label: a vetoed goal, an e-stop."""

    x: float
    y: float
    label: str


def _moved(points: list[tuple[float, float]], x: float, y: float) -> bool:
    return not points or abs(points[-1][0] - x) > SAME_SPOT or abs(points[-1][1] - y) > SAME_SPOT


def track_of(recording: RecordingFile) -> Track:
    """The robot's path from `robot/odom` and where people were seen on `world/humans`."""
    prefix = keys.prefix(recording.robot) + "/"
    odom, humans = prefix + keys.ODOM.path, prefix + keys.HUMANS.path
    found = Track()
    for message in recording.messages:
        try:
            if message.key == odom:
                pose = decode(message.data, Odometry).pose
                if _moved(found.path, pose.x, pose.y):
                    found.path.append((pose.x, pose.y))
            elif message.key == humans:
                for person in decode(message.data, PerceivedHumans).humans:
                    seen = found.people.setdefault(person.name, [])
                    if _moved(seen, person.pose.x, person.pose.y):
                        seen.append((person.pose.x, person.pose.y))
        except Undecodable:
            continue  # the timeline lists it
    return found


def _grouped(points: Iterable[tuple[float, float, str, float]]) -> list[Mark]:
    """Marks at one spot become one, labelled "what @ t1, t2 s"."""
    spots: list[tuple[float, float, str, list[float]]] = []
    # Each spot by its cell of a SAME_SPOT grid (one spot to a cell): a point's spot is in its own
    # cell or one next to it, so each point is grouped in constant time, not against every spot.
    cells: dict[tuple[str, int, int], int] = {}
    for x, y, what, t in points:
        cx, cy = _cell(x), _cell(y)
        near = [
            i
            for dx in (-1, 0, 1)
            for dy in (-1, 0, 1)
            if (i := cells.get((what, cx + dx, cy + dy))) is not None
            and abs(spots[i][0] - x) <= SAME_SPOT
            and abs(spots[i][1] - y) <= SAME_SPOT
        ]
        if near:
            spots[min(near)][3].append(t)  # the first spot made, as when every spot was tried in order
        else:
            cells[what, cx, cy] = len(spots)
            spots.append((x, y, what, [t]))
    marks = []
    for x, y, what, times in spots:
        shown = ", ".join(f"{t:.1f}" for t in times[:LABEL_TIMES])
        more = f" (+{len(times) - LABEL_TIMES})" if len(times) > LABEL_TIMES else ""
        marks.append(Mark(x, y, f"{what} @ {shown} s{more}"))
    return marks


def _cell(value: float) -> int:
    # Clamped: a coordinate of 1e308 from a crafted file would overflow; nothing is drawn that far out.
    return math.floor(max(-1e12, min(1e12, value / SAME_SPOT)))


def vetoed_goals(rows: Iterable[Row]) -> list[Mark]:
    """Where vetoed commands and plans would have sent the base, labelled with the rule and time."""
    return _grouped(
        (r.target[0], r.target[1], r.rule or "vetoed", r.t)
        for r in rows
        if r.decision is Decision.VETOED and r.target is not None
    )


def estop_points(rows: Iterable[Row]) -> list[Mark]:
    """Where the robot stood when the e-stop latched."""
    return _grouped(
        (r.state.x, r.state.y, "e-stop", r.t)
        for r in rows
        if r.decision is Decision.LATCHED and r.state.x is not None and r.state.y is not None
    )


def _bounds(world: World | None, keep_out: Sequence[KeepOut], points: list[tuple[float, float]]) -> list[float]:
    xs = [p[0] for p in points]
    ys = [p[1] for p in points]
    if world is not None:
        shapes = [Polygon(r.polygon) for r in world.rooms] + [wall_shape(w) for w in world.walls]
        shapes += [Polygon(k.polygon) for k in keep_out]
        for shape in shapes:
            x0, y0, x1, y1 = shape.bounds
            xs += [x0, x1]
            ys += [y0, y1]
    if not xs:
        return [-1.0, 1.0, -1.0, 1.0]
    return [min(xs) - MARGIN, max(xs) + MARGIN, min(ys) - MARGIN, max(ys) + MARGIN]


def draw_map(
    output: Path,
    title: str,
    world: World | None,
    keep_out: Sequence[KeepOut],
    track: Track,
    vetoes: Sequence[Mark] = (),
    estops: Sequence[Mark] = (),
) -> None:
    """Write the map to `output` (PNG). `keep_out` are the zones in force (the world's and the policy's)."""
    marks = [(m.x, m.y) for m in (*vetoes, *estops)]
    people = [p for seen in track.people.values() for p in seen]
    x0, x1, y0, y1 = _bounds(world, keep_out, track.path + marks + people)
    height = min(max(WIDTH * (y1 - y0) / max(x1 - x0, 1e-6), HEIGHT_RANGE[0]), HEIGHT_RANGE[1])
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    figure = Figure(figsize=(WIDTH, height), dpi=DPI)
    FigureCanvasAgg(figure)
    ax = figure.add_subplot()
    if world is not None:
        _draw_world(ax, world, keep_out)
    _draw_people(ax, track.people)
    if track.path:
        xs, ys = zip(*track.path, strict=True)
        ax.plot(xs, ys, color="tab:blue", linewidth=1.8, label="robot path", zorder=5)
        ax.plot(*track.path[0], "o", color="tab:green", markersize=10, markeredgecolor="black", label="start", zorder=6)
        # Above the e-stop marker: a run often ends where the e-stop stopped it.
        ax.plot(*track.path[-1], "s", color="tab:blue", markersize=8, markeredgecolor="white", label="end", zorder=9)
    _draw_marks(ax, vetoes, "vetoed goal", "darkred", marker="X", color="red", markersize=13, zorder=7)
    _draw_marks(ax, estops, "e-stop latched", "red", marker="H", color="gold", markersize=15, zorder=8)
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, color="#dddddd", linewidth=0.5, zorder=0)
    ax.set_title(title)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0, fontsize=9)
    figure.savefig(output, format="png", bbox_inches="tight")


def _draw_world(ax: Axes, world: World, keep_out: Sequence[KeepOut]) -> None:
    model = WorldModel(world)
    for i, room in enumerate(world.rooms):
        shape = model.room_shapes[room.id]
        ax.add_patch(_patch(shape, ROOM_COLOURS[i % len(ROOM_COLOURS)], edge="#bbbbbb", zorder=1))
        # In the top left corner, where furniture and the path seldom are; else anywhere inside.
        x0, _, _, y1 = shape.bounds
        corner = Point(x0 + LABEL_INSET, y1 - LABEL_INSET)
        inside = shape.contains(corner)
        spot = corner if inside else shape.representative_point()
        ha, va = ("left", "top") if inside else ("center", "center")
        ax.text(spot.x, spot.y, room.name, ha=ha, va=va, fontsize=10, color="#777777", style="italic")
    for i, wall in enumerate(world.walls):
        ax.add_patch(_patch(wall_shape(wall), "#555555", zorder=3, label="walls" if i == 0 else None))
    for i, item in enumerate(world.furniture):
        shape = model.footprint(item)
        colour = tuple(item.rgba[:3])
        ax.add_patch(_patch(shape, colour, edge="#333333", alpha=0.85, zorder=3, label="furniture" if i == 0 else None))
        ax.text(item.center[0], item.center[1], item.name, ha="center", va="center", fontsize=7, zorder=4)
    for i, zone in enumerate(keep_out):
        shape = Polygon(zone.polygon)
        label = "keep-out zone" if i == 0 else None
        ax.add_patch(_patch(shape, (0.9, 0.1, 0.1, 0.15), edge="red", hatch="//", zorder=2, label=label))
        # Along its bottom edge, clear of the goals vetoed inside it.
        x0, y0, x1, _ = shape.bounds
        bottom = Point((x0 + x1) / 2, y0 + LABEL_INSET)
        spot = bottom if shape.contains(bottom) else shape.representative_point()
        ax.text(spot.x, spot.y, zone.name, ha="center", va="bottom", fontsize=9, color="darkred", weight="bold")


def _draw_marks(ax: Axes, marks: Sequence[Mark], name: str, edge: str, **style: Any) -> None:
    """The marks as one series, the first MAX_LABELS labelled."""
    if not marks:
        return
    xs, ys = [m.x for m in marks], [m.y for m in marks]
    ax.plot(xs, ys, linestyle="none", markeredgecolor=edge, label=name + _unnamed(len(marks), "labelled"), **style)
    for mark in marks[:MAX_LABELS]:
        _label(ax, mark, edge)


def _unnamed(count: int, verb: str) -> str:
    """For the legend: how many of `count` things are drawn without their label."""
    return f" ({count - MAX_LABELS} of {count} not {verb})" if count > MAX_LABELS else ""


def _draw_people(ax: Axes, people: dict[str, list[tuple[float, float]]]) -> None:
    for i, (name, seen) in enumerate(people.items()):
        xs, ys = zip(*seen, strict=True)
        ax.plot(xs, ys, ":", color="darkorange", linewidth=1.0, zorder=4)
        label = "people seen" + _unnamed(len(people), "named") if i == 0 else None
        ax.plot(xs, ys, "o", color="darkorange", markersize=6, label=label, zorder=4)
        if i < MAX_LABELS:
            ax.annotate(name, seen[-1], xytext=(6, 6), textcoords="offset points", fontsize=8, color="darkorange")


def _patch(
    shape: Polygon, face: object, edge: str = "none", alpha: float | None = None, **kwargs: object
) -> PolygonPatch:
    from matplotlib.patches import Polygon as PolygonPatch

    return PolygonPatch(list(shape.exterior.coords), closed=True, facecolor=face, edgecolor=edge, alpha=alpha, **kwargs)


def _label(ax: Axes, mark: Mark, colour: str) -> None:
    box = {"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": colour, "alpha": 0.8}
    ax.annotate(
        mark.label, (mark.x, mark.y), xytext=(8, -12), textcoords="offset points", fontsize=8, color=colour, bbox=box
    ).set_zorder(9)
