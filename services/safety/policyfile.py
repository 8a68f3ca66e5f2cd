"""The safety policy file: what safety enforces, validated at start, fixed while it runs.

A policy is YAML or TOML (by suffix). Every field is bounded in its type; an unknown or malformed
entry is refused naming it (`$.base.max_linear_speed`). A policy may only tighten what the robot
itself allows: speeds and payload against the world file's robot, joint positions and velocities
against the arm's URDF (read through pinocchio). `Limits` is the result: the effective numbers the
checks use. The sha256 of the file's bytes names the policy in every safety event and heartbeat;
changing the policy means restarting safety.
"""

from __future__ import annotations

import hashlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import msgspec
import numpy as np
from msgspec import Meta
from shapely.geometry import Polygon as ShapelyPolygon
from shapely.ops import unary_union

from schemas.common import Id, Name, Text
from schemas.robot import ARM_JOINTS
from schemas.world import KeepOut, Polygon, RobotSpec, Room
from services.bundled import DEFAULT_POLICY
from services.datafile import decode_struct, read_bytes

if TYPE_CHECKING:  # the arm is handed in: whoever only needs DEFAULT_POLICY (the recorder) loads no pinocchio
    from services.robotmodel import ArmModel

Positive = Annotated[float, Meta(gt=0.0, le=1000.0)]
Fraction = Annotated[float, Meta(ge=0.0, le=1.0)]
Coordinate = Annotated[float, Meta(ge=-10.0, le=10.0)]


class PolicyError(Exception):
    """The policy file cannot be used; the message names the file and the entry."""


class Section(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    pass


class BasePolicy(Section):
    max_linear_speed: Annotated[float, Meta(gt=0.0, le=3.0)]  # m/s
    max_angular_speed: Annotated[float, Meta(gt=0.0, le=6.0)]  # rad/s
    max_linear_acceleration: Annotated[float, Meta(gt=0.0, le=20.0)]  # m/s^2
    max_angular_acceleration: Annotated[float, Meta(gt=0.0, le=40.0)]  # rad/s^2
    # A cmd_vel is refused if holding it this long would leave the map or enter a keep-out zone.
    cmd_vel_horizon: Annotated[float, Meta(gt=0.0, le=10.0)] = 1.0  # s
    # Added around the base's footprint (half-diagonal) when checking keep-out zones.
    footprint_margin: Annotated[float, Meta(ge=0.0, le=2.0)] = 0.0  # m


class JointPolicy(Section):
    """Tighter limits for one joint; what is left out is the URDF's."""

    lower: Annotated[float, Meta(ge=-10.0, le=10.0)] | None = None  # rad
    upper: Annotated[float, Meta(ge=-10.0, le=10.0)] | None = None  # rad
    velocity: Annotated[float, Meta(gt=0.0, le=10.0)] | None = None  # rad/s


class ArmPolicy(Section):
    max_joint_speed: Annotated[float, Meta(gt=0.0, le=10.0)] | None = None  # rad/s, every joint
    joints: dict[Annotated[str, Meta(max_length=64)], JointPolicy] = {}


class Point3(Section):
    x: Coordinate
    y: Coordinate
    z: Coordinate


class WorkspacePolicy(Section):
    """A box the end effector (the grasp point) must stay in, in the base frame (metres, z up from the floor)."""

    min: Point3
    max: Point3


class PayloadPolicy(Section):
    max_mass: Annotated[float, Meta(gt=0.0, le=1000.0)]  # kg


class GripperPolicy(Section):
    max_force: Annotated[float, Meta(gt=0.0, le=1000.0)]  # N


class HumanPolicy(Section):
    """Speed and separation: full speed beyond `slow_distance` (D), `reduced_speed_scale` of it inside,
    stopped inside `stop_distance` (d). Distances from the base's footprint or the end effector,
    whichever is nearer, to the person's body (`person_radius` around where they stand). A tighter
    scale applies at once, a looser one only `release_margin` beyond the boundary."""

    slow_distance: Annotated[float, Meta(gt=0.0, le=20.0)]  # m
    stop_distance: Annotated[float, Meta(ge=0.0, le=20.0)]  # m
    reduced_speed_scale: Annotated[float, Meta(gt=0.0, le=1.0)]
    # People are reported by where they stand; distances are to their body, this far around it.
    person_radius: Annotated[float, Meta(ge=0.0, le=2.0)] = 0.2  # m
    # With no report of people for this long, someone may be near: reduced speed.
    unseen_after: Annotated[float, Meta(gt=0.0, le=60.0)] = 1.0  # s
    # Back to a looser scale only this far beyond the boundary that tightened it.
    release_margin: Annotated[float, Meta(ge=0.0, le=2.0)] = 0.1  # m


class RatePolicy(Section):
    max_goals_per_second: Annotated[float, Meta(gt=0.0, le=10000.0)]  # per action
    max_cmd_vel_per_second: Annotated[float, Meta(gt=0.0, le=100000.0)]
    # The bucket holds this many seconds' worth of commands: bursts up to that pass.
    burst_seconds: Annotated[float, Meta(gt=0.0, le=10.0)] = 0.5


class MonitorPolicy(Section):
    """What safety watches while the robot moves."""

    # Measured speed may exceed the allowed speed by this fraction plus `speed_slack` before the
    # e-stop trips, for `trip_after` consecutive samples (measurements are noisy).
    speed_tolerance: Fraction = 0.1
    speed_slack: Annotated[float, Meta(ge=0.0, le=1.0)] = 0.05  # m/s or rad/s
    trip_after: Annotated[int, Meta(ge=1, le=100)] = 3
    # After the allowed speed drops, the robot gets this long to react before it must brake.
    reaction_time: Annotated[float, Meta(ge=0.0, le=5.0)] = 0.3  # s
    # Odometry or joint states older than this are unknown: motion commands are refused, and the
    # watchdog trips the e-stop if the robot was last seen moving.
    state_max_age: Annotated[float, Meta(gt=0.0, le=10.0)] = 0.5  # s


class IncidentPolicy(Section):
    """What safety does with its memory of incidents (services/safety/incidents.py): only ever more
    careful. A pause for a person closer than `near_miss_distance` is a near-miss; `caution_count`
    incidents (not cleared) within `caution_radius` of one another make a caution zone, where the
    robot keeps to `caution_speed_scale` of its limits until an operator clears it; a plan check warns
    of incidents within `warn_radius` of a place the plan goes or an object it handles."""

    near_miss_distance: Annotated[float, Meta(ge=0.0, le=5.0)] = 0.15  # m
    caution_count: Annotated[int, Meta(ge=1, le=1000)] = 3
    caution_radius: Annotated[float, Meta(gt=0.0, le=20.0)] = 1.0  # m
    caution_speed_scale: Annotated[float, Meta(gt=0.0, le=1.0)] = 0.5
    warn_radius: Annotated[float, Meta(gt=0.0, le=20.0)] = 1.0  # m


class KeepOutPolicy(Section):
    id: Id
    name: Name
    polygon: Polygon
    reason: Text = ""


class Policy(Section):
    base: BasePolicy
    arm: ArmPolicy
    workspace: WorkspacePolicy
    payload: PayloadPolicy
    gripper: GripperPolicy
    humans: HumanPolicy
    rate: RatePolicy
    monitor: MonitorPolicy = MonitorPolicy()
    incidents: IncidentPolicy = IncidentPolicy()
    # In addition to the world file's zones, which a policy cannot remove.
    keep_out: list[KeepOutPolicy] = []


@dataclass(frozen=True)
class JointLimit:
    lower: float
    upper: float
    velocity: float


@dataclass(frozen=True)
class Limits:
    """The effective numbers: the policy's, checked against the robot's own."""

    policy: Policy
    path: Path
    hash: str
    joints: dict[str, JointLimit]
    keep_out: tuple[KeepOut, ...]

    def summary(self) -> dict[str, Any]:
        """The effective limits as plain data, for people and tools."""
        policy = msgspec.to_builtins(self.policy)
        policy.pop("keep_out", None)
        return {
            "path": str(self.path),
            "hash": self.hash,
            **policy,
            "joints": {name: vars(limit) for name, limit in self.joints.items()},
            "keep_out": [{"id": z.id, "name": z.name, "reason": z.reason} for z in self.keep_out],
        }


def load_policy(
    path: Path | None, robot: RobotSpec, arm: ArmModel, world_zones: list[KeepOut], rooms: Sequence[Room] = ()
) -> Limits:
    """Read, validate and resolve the policy; PolicyError names the entry that is wrong. With the
    world's `rooms`, a keep-out zone outside every one of them is refused too (safety passes them)."""
    path = path or DEFAULT_POLICY
    if path.suffix not in (".toml", ".yaml", ".yml"):
        raise PolicyError(f"policy file {path}: use .toml, .yaml or .yml")
    return parse_policy(read_bytes(path, "policy", PolicyError), path, robot, arm, world_zones, rooms)


def parse_policy(
    data: bytes, path: Path, robot: RobotSpec, arm: ArmModel, world_zones: list[KeepOut], rooms: Sequence[Room] = ()
) -> Limits:
    """The policy from the bytes of a file named `path` (a file kept in a recording, say)."""
    if path.suffix not in (".toml", ".yaml", ".yml"):
        raise PolicyError(f"policy file {path}: use .toml, .yaml or .yml")
    policy = decode_struct(data, path, Policy, "policy", PolicyError)
    digest = "sha256:" + hashlib.sha256(data).hexdigest()
    return resolve(policy, path, digest, robot, arm, world_zones, rooms)


def resolve(
    policy: Policy,
    path: Path,
    digest: str,
    robot: RobotSpec,
    arm: ArmModel,
    world_zones: list[KeepOut],
    rooms: Sequence[Room] = (),
) -> Limits:
    def bad(entry: str, why: str) -> PolicyError:
        return PolicyError(f"policy file {path}: {entry}: {why}")

    base = policy.base
    if base.max_linear_speed > robot.max_linear_speed:
        raise bad(
            "base.max_linear_speed",
            f"{base.max_linear_speed:g} m/s is above the robot's own {robot.max_linear_speed:g} m/s",
        )
    if base.max_angular_speed > robot.max_angular_speed:
        raise bad(
            "base.max_angular_speed",
            f"{base.max_angular_speed:g} rad/s is above the robot's own {robot.max_angular_speed:g} rad/s",
        )
    for entry, value, own, unit in (
        ("base.max_linear_acceleration", base.max_linear_acceleration, robot.max_linear_acceleration, "m/s^2"),
        ("base.max_angular_acceleration", base.max_angular_acceleration, robot.max_angular_acceleration, "rad/s^2"),
    ):
        # Safety's monitors expect the robot to brake this hard; the robot cannot brake harder.
        if value > own:
            raise bad(entry, f"{value:g} {unit} is above the robot's own {own:g} {unit}")
    if policy.payload.max_mass > robot.payload:
        raise bad("payload.max_mass", f"{policy.payload.max_mass:g} kg is above the arm's payload {robot.payload:g} kg")
    humans = policy.humans
    if humans.stop_distance >= humans.slow_distance:
        raise bad(
            "humans.stop_distance",
            f"{humans.stop_distance:g} m must be less than humans.slow_distance {humans.slow_distance:g} m",
        )
    box = policy.workspace
    for axis in ("x", "y", "z"):
        if getattr(box.min, axis) >= getattr(box.max, axis):
            raise bad(f"workspace.min.{axis}", f"must be less than workspace.max.{axis}")
    if box.min.z < 0.0:
        # Nothing else keeps the hand out of the floor: the workspace box is its only bound.
        raise bad("workspace.min.z", f"{box.min.z:g} m is below the floor (z is up from the floor)")
    joints = _joint_limits(policy.arm, arm, bad)
    zones = list(world_zones)
    ids = {zone.id for zone in zones}
    floor = unary_union([ShapelyPolygon(room.polygon) for room in rooms]) if rooms else None
    for i, zone in enumerate(policy.keep_out):
        entry = f"keep_out[{i}] ({zone.id})"
        if zone.id in ids:
            raise bad(entry, "a keep-out zone with this id already exists (the world file's zones always apply)")
        shape = ShapelyPolygon(zone.polygon)
        if not shape.is_valid or shape.area <= 0:
            raise bad(entry, "the polygon is not a simple polygon with an area")
        if floor is not None and not floor.intersects(shape):
            # Corners in the wrong place (or frame): the zone keeps the robot out of nothing.
            raise bad(entry, "is outside every room of the world; it would keep the robot out of nothing")
        ids.add(zone.id)
        zones.append(KeepOut(id=zone.id, name=zone.name, polygon=zone.polygon, reason=zone.reason))
    return Limits(policy, path, digest, joints, tuple(zones))


def _joint_limits(policy: ArmPolicy, arm: ArmModel, bad: Callable[[str, str], PolicyError]) -> dict[str, JointLimit]:
    unknown = sorted(set(policy.joints) - set(ARM_JOINTS))
    if unknown:
        raise bad(f"arm.joints.{unknown[0]}", f"no such joint; the arm's joints are {', '.join(ARM_JOINTS)}")
    limits: dict[str, JointLimit] = {}
    for name, lower, upper, velocity in zip(
        arm.joint_names, np.asarray(arm.lower), np.asarray(arm.upper), np.asarray(arm.max_velocity), strict=True
    ):
        lower, upper, velocity = float(lower), float(upper), float(velocity)
        tighter = policy.joints.get(name, JointPolicy())
        entry = f"arm.joints.{name}"
        if policy.max_joint_speed is not None:
            if policy.max_joint_speed > velocity:
                raise bad(
                    "arm.max_joint_speed",
                    f"{policy.max_joint_speed:g} rad/s is above {name}'s URDF limit {velocity:g} rad/s",
                )
            velocity = policy.max_joint_speed
        if tighter.velocity is not None:
            if tighter.velocity > velocity:
                raise bad(f"{entry}.velocity", f"{tighter.velocity:g} rad/s is looser than {velocity:g} rad/s")
            velocity = tighter.velocity
        if tighter.lower is not None:
            if tighter.lower < lower:
                raise bad(f"{entry}.lower", f"{tighter.lower:g} rad is below the URDF's {lower:g} rad")
            lower = tighter.lower
        if tighter.upper is not None:
            if tighter.upper > upper:
                raise bad(f"{entry}.upper", f"{tighter.upper:g} rad is above the URDF's {upper:g} rad")
            upper = tighter.upper
        if lower >= upper:
            raise bad(entry, f"lower {lower:g} rad is not below upper {upper:g} rad")
        limits[name] = JointLimit(lower, upper, velocity)
    return limits
