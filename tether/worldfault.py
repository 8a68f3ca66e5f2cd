"""`tether world fault`: inject a fault into the SIMULATED world (sim/fault), for tests and demos of recovery."""

from __future__ import annotations

from typing import Annotated

import typer

from schemas import keys
from schemas.common import ErrorKind, ServiceError
from schemas.world import FaultKind, InjectFault
from services.errors import CallError
from tether.cli import client, out, world_failed
from tether.output import conclude, shown


def world_fault(
    ctx: typer.Context,
    kind: Annotated[FaultKind, typer.Argument(help="slip, block, hide or clear.")],
    target: Annotated[
        str,
        typer.Argument(
            metavar="[TARGET]",
            help="block: a room or doorway id (kitchen, kitchen-living_room); hide: an object id; "
            "slip: optionally the object id whose carry it waits for; clear: none.",
        ),
    ] = "",
    as_json: Annotated[
        bool,
        typer.Option("--json", help="Print one JSON object: status, and kind, target, message, position or the error."),
    ] = False,
) -> None:
    """Inject a fault into the SIMULATED world, for tests and demos (not a robot action).

    Recorded like `world move`.

    slip: what the gripper holds on its next carry slips out once the base has driven 0.3 m; it lands
    on a furniture top within the arm's reach, else on the floor beside the base. block ROOM_OR_DOOR:
    a box across the doorway (ids: the two rooms, `kitchen-living_room`) or where "go to the room"
    parks. hide OBJECT: the object taken outside the house, out of every camera's sight. clear: all
    of these undone, hidden objects put back.

    Exit 0 injected (status 'injected'), 2 refused (status 'refused': an unknown target, which the
    error lists the known ones of; a slip already armed, the object in the gripper), 3 no simulator
    (status 'unreachable'), 1 when the simulator failed otherwise.
    """
    with client(ctx) as node:
        if not node.is_alive("sim", 2.0):
            why = "no simulator reachable: start it with `tether up` or `tether run sim`"
            world_failed(ServiceError(kind=ErrorKind.UNAVAILABLE, message=why), as_json)
        try:
            reply = node.call(keys.SIM_FAULT, InjectFault(kind=kind, target=target), timeout=10.0)
        except CallError as exc:
            world_failed(exc.error, as_json)
    if isinstance(reply, ServiceError):
        world_failed(reply, as_json)
    p = reply.position
    position = None if p is None else {"x": p.x, "y": p.y, "z": p.z}
    document = {
        "status": "injected",
        "kind": str(reply.kind),
        "target": reply.target,
        "message": reply.message,
        "position": position,
    }
    conclude(out, as_json, document, f"{shown(reply.kind)}: {shown(reply.message)}")
