"""The resolver's configuration: which world it grounds plans in and how it picks spots and poses."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

Distance = Annotated[float, Meta(ge=0.0, le=3.0)]


class ResolverConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # A bundled world's name ("household") or a path to a world file.
    world: Annotated[str, Meta(min_length=1, max_length=1000)] = "household"
    # A put-down spot is this far in from the table edge the robot stands at...
    place_inset: Distance = 0.15
    # ...and at least this far (xy, centre to centre) from everything already on that top.
    place_clearance: Distance = 0.15
    # Where the base stops when told to go to a person, and to an object lying on the floor.
    human_standoff: Annotated[float, Meta(ge=0.3, le=3.0)] = 0.8
    object_standoff: Annotated[float, Meta(ge=0.2, le=2.0)] = 0.6
