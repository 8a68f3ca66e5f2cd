"""The resolver's configuration: which world it grounds plans in, how sure a match must be, how it
remembers what perception saw, and how it picks spots and poses."""

from __future__ import annotations

from typing import Annotated

import msgspec
from msgspec import Meta

Distance = Annotated[float, Meta(ge=0.0, le=3.0)]


class ResolverConfig(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # A bundled world's name ("household") or a path to a world file.
    world: Annotated[str, Meta(min_length=1, max_length=1000)] = "household"
    # A near-miss name ("cofee mug") resolves when its match score is at least this (0..1), with a
    # warning; below it the plan is refused with the closest names. Exact names score 1.
    min_confidence: Annotated[float, Meta(ge=0.5, le=1.0)] = 0.8
    # Two near-misses within this of each other's score are ambiguous, not a choice.
    confidence_margin: Annotated[float, Meta(ge=0.0, le=0.5)] = 0.05
    # "near": within this (xy, metres) of the other thing (of a furniture's footprint).
    near_distance: Distance = 0.75
    # Coordinates a plan attached to a named entity farther than this from it: a warning.
    coordinate_tolerance: Distance = 0.5
    # An object not seen by perception for this long (seconds) is stale: still used, with a warning.
    stale_after: Annotated[float, Meta(gt=0.0, le=86400.0)] = 60.0
    # A new sighting within this (metres) of the remembered one refines it; farther, the object moved.
    move_tolerance: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.05
    # Successful resolutions kept for identical plans while the world does not change.
    cache_size: Annotated[int, Meta(ge=0, le=100000)] = 256
    # A put-down spot is this far in from the table edge the robot stands at...
    place_inset: Distance = 0.15
    # ...and at least this far (xy, centre to centre) from everything already on that top.
    place_clearance: Distance = 0.15
    # Where the base stops when told to go to a person, and to an object lying on the floor.
    human_standoff: Annotated[float, Meta(ge=0.3, le=3.0)] = 0.8
    object_standoff: Annotated[float, Meta(ge=0.2, le=2.0)] = 0.6
