"""The resolver's configuration: which world it grounds plans in, how sure a match must be, how it
remembers what perception saw, and how it picks spots and poses."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec
from msgspec import Meta

Distance = Annotated[float, Meta(ge=0.0, le=3.0)]
Phrase = Annotated[str, Meta(min_length=1, max_length=100)]
# A place location that means "where the object was before it was picked up".
PUT_BACK_PHRASES = (
    "where it was found",
    "where it was",
    "where you found it",
    "where it came from",
    "where it was before",
    "where it belongs",
    "back",
    "back where it was",
    "its place",
    "its spot",
    "its original place",
    "its original position",
    "original place",
    "original position",
)


# Odometry older than this (seconds since it arrived) is not where the robot is (odom_max_age).
ODOM_MAX_AGE = 1.0


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
    # Odometry older than this (seconds since it arrived) is no pose: a move relative to the robot,
    # or a choice by where it stands, is refused (precondition) until odometry comes again.
    odom_max_age: Annotated[float, Meta(gt=0.0, le=60.0)] = ODOM_MAX_AGE
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
    # A place at a person ("bring it to me"): "surface" puts the object down on the free furniture
    # top nearest them; "hand" drives to them (human_standoff) and keeps holding it out.
    deliver: Literal["surface", "hand"] = "surface"
    # "surface": no top whose free spot is within this (xy, metres) of the person: refused.
    deliver_max_distance: Annotated[float, Meta(gt=0.0, le=20.0)] = 3.0
    # "surface": the spot is at most this far (xy) from the base at the top's approach pose, where
    # the arm reaches it without stretching.
    deliver_reach: Annotated[float, Meta(ge=0.3, le=1.2)] = 0.85
    # Place locations meaning "where the object stood before this plan (or the gripper) took it".
    # Compared without case, articles or punctuation; a name the world knows wins over them.
    put_back_phrases: Annotated[tuple[Phrase, ...], Meta(max_length=100)] = PUT_BACK_PHRASES
