"""The safety policy file: loaded and named by its hash, refused naming the entry when it is wrong,
and applied when it tightens the robot's own limits (never when it loosens them)."""

from __future__ import annotations

import copy
import hashlib
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec
import pytest

from schemas.common import Pose2D
from schemas.robot import FollowJointTrajectoryGoal, GripperCommandGoal, NavigateToPoseGoal, TrajectoryPoint, Twist
from schemas.safety import Rule
from schemas.world import RobotSpec, World
from services.robotmodel import ArmModel
from services.safety.errors import Vetoed
from services.safety.policy import JOINT_LIMIT_MARGIN, SafetyPolicy
from services.safety.policyfile import DEFAULT_POLICY, Limits, PolicyError, load_policy
from services.worldmodel import WorldModel, load_world

WORLD = load_world()
ROBOT = WORLD.robot
DEFAULT_BYTES = DEFAULT_POLICY.read_bytes()
DEFAULT_DATA: dict[str, Any] = msgspec.toml.decode(DEFAULT_BYTES)
EPS = 1e-3
ARM = [f"panda_joint{i}" for i in range(1, 8)]
HOME = [0.0, -1.2, 0.0, -2.7, 0.0, 1.5, 0.785]
NOW = dict(zip(ARM, HOME, strict=True))
START = Pose2D(x=6.0, y=1.2)
RADIUS = math.hypot(ROBOT.base_size.x, ROBOT.base_size.y) / 2
NURSERY = {
    "id": "nursery",
    "name": "nursery",
    "reason": "the baby is asleep",
    "polygon": [[1.0, 6.0], [3.0, 6.0], [3.0, 8.0], [1.0, 8.0]],
}


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    return ArmModel(ROBOT.arm_urdf)


def load(path: Path | None, arm: ArmModel) -> Limits:
    return load_policy(path, ROBOT, arm, WORLD.keep_out)


def write_yaml(path: Path, data: dict[str, Any]) -> Path:
    path.write_bytes(msgspec.yaml.encode(data))
    return path


def changed(**entries: Any) -> dict[str, Any]:
    """The default policy with entries set by dotted path ("base.max_linear_speed")."""
    data = copy.deepcopy(DEFAULT_DATA)
    for dotted, value in entries.items():
        *parents, last = dotted.split(".")
        node = data
        for key in parents:
            node = node.setdefault(key, {})
        node[last] = value
    return data


def trajectory(q: list[float], t: float) -> FollowJointTrajectoryGoal:
    return FollowJointTrajectoryGoal(joint_names=ARM, points=[TrajectoryPoint(positions=q, time_from_start=t)])


def with_joint(name: str, value: float) -> list[float]:
    q = list(HOME)
    q[ARM.index(name)] = value
    return q


# Loading


def test_the_default_policy_loads_and_is_named_by_the_sha256_of_its_bytes(arm: ArmModel) -> None:
    limits = load(None, arm)
    digest = hashlib.sha256(DEFAULT_BYTES).hexdigest()
    assert limits.path == DEFAULT_POLICY
    assert limits.hash == "sha256:" + digest
    assert load(DEFAULT_POLICY, arm).hash == limits.hash
    # The URDF's positions, the policy's speed for every joint, the world's zones and no others.
    assert list(limits.joints) == ARM
    for name, lower, upper in zip(ARM, arm.lower, arm.upper, strict=True):
        assert (limits.joints[name].lower, limits.joints[name].upper) == (lower, upper)
        assert limits.joints[name].velocity == DEFAULT_DATA["arm"]["max_joint_speed"]
    assert limits.keep_out == tuple(WORLD.keep_out)
    assert limits.policy.base.max_linear_speed == DEFAULT_DATA["base"]["max_linear_speed"]


@pytest.mark.parametrize("suffix", [".yaml", ".yml"])
def test_the_same_policy_in_yaml_gives_the_same_limits(tmp_path: Path, arm: ArmModel, suffix: str) -> None:
    path = write_yaml(tmp_path / f"policy{suffix}", DEFAULT_DATA)
    toml, yaml = load(None, arm), load(path, arm)
    assert yaml.policy == toml.policy
    assert yaml.joints == toml.joints and yaml.keep_out == toml.keep_out
    assert yaml.hash == "sha256:" + hashlib.sha256(path.read_bytes()).hexdigest() != toml.hash


def test_any_change_to_the_file_changes_its_hash_even_a_comment(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.toml"
    path.write_bytes(DEFAULT_BYTES + b"\n# reviewed\n")
    limits = load(path, arm)
    assert limits.policy == load(None, arm).policy
    assert limits.hash != load(None, arm).hash


# Refused, naming the entry


def urdf(arm: ArmModel, what: str, name: str = "panda_joint1") -> float:
    return float(getattr(arm, what)[ARM.index(name)])


Case = Callable[[ArmModel, RobotSpec], dict[str, Any]]
WRONG: list[tuple[str, Case, list[str]]] = [
    ("unknown-field", lambda a, r: changed(**{"base.top_speed": 1.0}), ["unknown field `top_speed`", "`$.base`"]),
    ("unknown-section", lambda a, r: changed(extras={"x": 1}), ["unknown field `extras`"]),
    ("missing-section", lambda a, r: {k: v for k, v in DEFAULT_DATA.items() if k != "payload"}, ["`payload`"]),
    (
        "wrong-type",
        lambda a, r: changed(**{"base.max_linear_speed": "fast"}),
        ["`$.base.max_linear_speed`", "`float`", "`str`"],
    ),
    ("not-an-int", lambda a, r: changed(**{"monitor.trip_after": 2.5}), ["`$.monitor.trip_after`", "`int`"]),
    ("zero-speed", lambda a, r: changed(**{"base.max_linear_speed": 0.0}), ["`$.base.max_linear_speed`", "> 0.0"]),
    (
        "scale-over-1",
        lambda a, r: changed(**{"humans.reduced_speed_scale": 1.0 + EPS}),
        ["$.humans.reduced_speed_scale"],
    ),
    ("trip-after-0", lambda a, r: changed(**{"monitor.trip_after": 0}), ["`$.monitor.trip_after`", ">= 1"]),
    ("off-bounds-box", lambda a, r: changed(**{"workspace.max.z": 10.0 + EPS}), ["`$.workspace.max.z`"]),
    (
        "faster-than-the-robot",
        lambda a, r: changed(**{"base.max_linear_speed": r.max_linear_speed + EPS}),
        ["base.max_linear_speed: 0.601 m/s is above the robot's own 0.6 m/s"],
    ),
    (
        "turning-faster-than-the-robot",
        lambda a, r: changed(**{"base.max_angular_speed": r.max_angular_speed + EPS}),
        ["base.max_angular_speed: 1.201 rad/s", "1.2 rad/s"],
    ),
    (
        "speeding-up-harder-than-the-robot",
        lambda a, r: changed(**{"base.max_linear_acceleration": r.max_linear_acceleration + EPS}),
        ["base.max_linear_acceleration: 1.501 m/s^2 is above the robot's own 1.5 m/s^2"],
    ),
    (
        "turning-up-harder-than-the-robot",
        lambda a, r: changed(**{"base.max_angular_acceleration": r.max_angular_acceleration + EPS}),
        ["base.max_angular_acceleration: 3.001 rad/s^2 is above the robot's own 3 rad/s^2"],
    ),
    (
        "reaction-time-too-long",
        lambda a, r: changed(**{"monitor.reaction_time": 5.0 + EPS}),
        ["`$.monitor.reaction_time`", "<= 5.0"],
    ),
    (
        "negative-person-radius",
        lambda a, r: changed(**{"humans.person_radius": -EPS}),
        ["`$.humans.person_radius`", ">= 0.0"],
    ),
    (
        "joints-faster-than-the-urdf",
        lambda a, r: changed(**{"arm.max_joint_speed": float(min(a.max_velocity)) + EPS}),
        ["arm.max_joint_speed: 2.176 rad/s is above", "URDF limit 2.175 rad/s"],
    ),
    (
        "joint-below-the-urdf",
        lambda a, r: changed(**{"arm.joints": {"panda_joint1": {"lower": urdf(a, "lower") - EPS}}}),
        ["arm.joints.panda_joint1.lower: -2.9681 rad is below the URDF's -2.9671 rad"],
    ),
    (
        "joint-above-the-urdf",
        lambda a, r: changed(**{"arm.joints": {"panda_joint4": {"upper": EPS}}}),
        ["arm.joints.panda_joint4.upper: 0.001 rad is above the URDF's 0 rad"],
    ),
    (
        "joint-faster-than-the-policy",
        lambda a, r: changed(
            **{"arm.joints": {"panda_joint7": {"velocity": DEFAULT_DATA["arm"]["max_joint_speed"] + EPS}}}
        ),
        ["arm.joints.panda_joint7.velocity: 1.501 rad/s is looser than 1.5 rad/s"],
    ),
    (
        "unknown-joint",
        lambda a, r: changed(**{"arm.joints": {"elbow": {"upper": 1.0}}}),
        ["arm.joints.elbow: no such joint", "panda_joint1"],
    ),
    (
        "empty-joint-range",
        lambda a, r: changed(**{"arm.joints": {"panda_joint2": {"lower": 0.5, "upper": 0.5}}}),
        ["arm.joints.panda_joint2: lower 0.5 rad is not below upper 0.5 rad"],
    ),
    (
        "payload-over-the-arm",
        lambda a, r: changed(**{"payload.max_mass": r.payload + EPS}),
        ["payload.max_mass: 3.001 kg is above the arm's payload 3 kg"],
    ),
    (
        "stop-at-slow",
        lambda a, r: changed(**{"humans.stop_distance": DEFAULT_DATA["humans"]["slow_distance"]}),
        ["humans.stop_distance: 1.5 m must be less than humans.slow_distance 1.5 m"],
    ),
    (
        "empty-workspace",
        lambda a, r: changed(**{"workspace.min.z": DEFAULT_DATA["workspace"]["max"]["z"]}),
        ["workspace.min.z: must be less than workspace.max.z"],
    ),
    (
        "reusing-the-worlds-zone",
        lambda a, r: changed(keep_out=[{**NURSERY, "id": "stairs"}]),
        ["keep_out[0] (stairs): a keep-out zone with this id already exists"],
    ),
    (
        "zone-twice",
        lambda a, r: changed(keep_out=[NURSERY, NURSERY]),
        ["keep_out[1] (nursery): a keep-out zone with this id already exists"],
    ),
    (
        "self-intersecting-zone",
        lambda a, r: changed(keep_out=[{**NURSERY, "polygon": [[1.0, 6.0], [3.0, 8.0], [3.0, 6.0], [1.0, 8.0]]}]),
        ["keep_out[0] (nursery): the polygon is not a simple polygon"],
    ),
    (
        "flat-zone",
        lambda a, r: changed(keep_out=[{**NURSERY, "polygon": [[1.0, 6.0], [2.0, 6.0], [3.0, 6.0]]}]),
        ["keep_out[0] (nursery)", "with an area"],
    ),
    (
        "zone-with-two-corners",
        lambda a, r: changed(keep_out=[{**NURSERY, "polygon": [[1.0, 6.0], [2.0, 6.0]]}]),
        ["`$.keep_out[0].polygon`"],
    ),
]


@pytest.mark.parametrize(("case", "fragments"), [(c, f) for _, c, f in WRONG], ids=[i for i, _, _ in WRONG])
def test_a_wrong_policy_is_refused_naming_the_file_and_the_entry(
    tmp_path: Path, arm: ArmModel, case: Case, fragments: list[str]
) -> None:
    path = write_yaml(tmp_path / "policy.yaml", case(arm, ROBOT))
    with pytest.raises(PolicyError) as refused:
        load(path, arm)
    message = str(refused.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message


RIGHT: list[tuple[str, Case]] = [
    ("as-fast-as-the-robot", lambda a, r: changed(**{"base.max_linear_speed": r.max_linear_speed})),
    ("turning-as-fast-as-the-robot", lambda a, r: changed(**{"base.max_angular_speed": r.max_angular_speed})),
    (
        "speeding-up-as-hard-as-the-robot",
        lambda a, r: changed(**{"base.max_linear_acceleration": r.max_linear_acceleration}),
    ),
    (
        "turning-up-as-hard-as-the-robot",
        lambda a, r: changed(**{"base.max_angular_acceleration": r.max_angular_acceleration}),
    ),
    ("joints-as-fast-as-the-urdf", lambda a, r: changed(**{"arm.max_joint_speed": float(min(a.max_velocity))})),
    ("joint-at-the-urdf", lambda a, r: changed(**{"arm.joints": {"panda_joint1": {"lower": urdf(a, "lower")}}})),
    ("joint-at-the-urdf-top", lambda a, r: changed(**{"arm.joints": {"panda_joint4": {"upper": 0.0}}})),
    ("payload-of-the-arm", lambda a, r: changed(**{"payload.max_mass": r.payload})),
    (
        "stop-inside-slow",
        lambda a, r: changed(**{"humans.stop_distance": DEFAULT_DATA["humans"]["slow_distance"] - EPS}),
    ),
    ("thin-workspace", lambda a, r: changed(**{"workspace.min.z": DEFAULT_DATA["workspace"]["max"]["z"] - EPS})),
    ("scale-of-1", lambda a, r: changed(**{"humans.reduced_speed_scale": 1.0})),
]


@pytest.mark.parametrize("case", [c for _, c in RIGHT], ids=[i for i, _ in RIGHT])
def test_a_policy_at_the_robots_own_limits_loads(tmp_path: Path, arm: ArmModel, case: Case) -> None:
    assert load(write_yaml(tmp_path / "policy.yaml", case(arm, ROBOT)), arm).hash.startswith("sha256:")


def test_a_missing_file_a_json_file_or_bad_syntax_is_refused(tmp_path: Path, arm: ArmModel) -> None:
    with pytest.raises(PolicyError, match=r"cannot read policy file .*missing\.toml"):
        load(tmp_path / "missing.toml", arm)
    json = tmp_path / "policy.json"
    json.write_bytes(msgspec.json.encode(DEFAULT_DATA))
    with pytest.raises(PolicyError, match=r"policy\.json: use \.toml, \.yaml or \.yml"):
        load(json, arm)
    broken = tmp_path / "policy.toml"
    broken.write_bytes(DEFAULT_BYTES + b"\n[[[\n")
    with pytest.raises(PolicyError, match=r"policy\.toml is not valid TOML"):
        load(broken, arm)
    twice = tmp_path / "twice.toml"
    twice.write_bytes(DEFAULT_BYTES + b"\n[base]\nmax_linear_speed = 0.1\n")
    with pytest.raises(PolicyError, match="is not valid TOML"):
        load(twice, arm)
    bad_yaml = tmp_path / "policy.yaml"
    bad_yaml.write_text("base: [unclosed\n")
    with pytest.raises(PolicyError, match="is not valid YAML"):
        load(bad_yaml, arm)


# Applied


# The coffee table's approach pose: from START the base drives there in a straight line.
COFFEE_TABLE = Pose2D(x=8.0, y=1.75, yaw=math.pi / 2)
# The flat with its walls and furniture taken away: keep-out zones alone decide where the base may go.
OPEN_FLOOR = msgspec.structs.replace(WORLD, walls=[], furniture=[], objects=[])


def checks(limits: Limits, arm: ArmModel, world: World = WORLD) -> SafetyPolicy:
    return SafetyPolicy(WorldModel(world), limits, arm)


def test_a_tightened_joint_range_is_enforced_between_the_new_and_the_old_limit(tmp_path: Path, arm: ArmModel) -> None:
    upper = 1.0
    path = write_yaml(tmp_path / "policy.yaml", changed(**{"arm.joints": {"panda_joint1": {"upper": upper}}}))
    tight, loose = checks(load(path, arm), arm), checks(load(None, arm), arm)
    assert tight.joint_limits["panda_joint1"].upper == upper
    assert tight.joint_limits["panda_joint1"].lower == urdf(arm, "lower")
    assert tight.joint_limits["panda_joint2"] == loose.joint_limits["panda_joint2"]
    between = trajectory(with_joint("panda_joint1", 1.5), 2.0)
    assert loose.check_trajectory(between, NOW, START)
    with pytest.raises(Vetoed) as refused:
        tight.check_trajectory(between, NOW, START)
    assert refused.value.rule is Rule.JOINT_LIMITS
    assert refused.value.values["upper_rad"] == pytest.approx(upper - JOINT_LIMIT_MARGIN)
    # The margin applies to the policy's limit as to the URDF's.
    assert tight.check_trajectory(
        trajectory(with_joint("panda_joint1", upper - JOINT_LIMIT_MARGIN - EPS), 2.0), NOW, START
    )
    with pytest.raises(Vetoed):
        tight.check_trajectory(
            trajectory(with_joint("panda_joint1", upper - JOINT_LIMIT_MARGIN + EPS), 2.0), NOW, START
        )


def test_a_tightened_joint_speed_is_enforced(tmp_path: Path, arm: ArmModel) -> None:
    speed = 1.0
    path = write_yaml(tmp_path / "policy.yaml", changed(**{"arm.joints": {"panda_joint7": {"velocity": speed}}}))
    tight = checks(load(path, arm), arm)
    assert tight.joint_limits["panda_joint7"].velocity == speed
    assert tight.joint_limits["panda_joint6"].velocity == DEFAULT_DATA["arm"]["max_joint_speed"]
    at = trajectory(with_joint("panda_joint7", HOME[6] + speed), 1.0)
    assert tight.check_trajectory(at, NOW, START)
    with pytest.raises(Vetoed) as refused:
        tight.check_trajectory(trajectory(with_joint("panda_joint7", HOME[6] + speed + 2 * EPS), 1.0), NOW, START)
    assert refused.value.rule is Rule.JOINT_SPEED
    assert refused.value.values == {"speed_rps": pytest.approx(speed + 2 * EPS), "limit_rps": speed}


def test_tightened_base_and_gripper_limits_are_enforced(tmp_path: Path, arm: ArmModel) -> None:
    path = write_yaml(
        tmp_path / "policy.yaml",
        changed(
            **{
                "base.max_linear_speed": 0.3,
                "base.max_angular_speed": 0.5,
                "gripper.max_force": 20.0,
                "payload.max_mass": 1.0,
            }
        ),
    )
    tight = checks(load(path, arm), arm)
    goal = NavigateToPoseGoal(pose=COFFEE_TABLE, max_speed=0.3)
    assert tight.check_navigation(goal, START).command.max_speed == 0.3
    # Not asked for, the tightened limits are filled in.
    filled = tight.check_navigation(NavigateToPoseGoal(pose=goal.pose), START).command
    assert (filled.max_speed, filled.max_turn_rate) == (0.3, 0.5)
    assert tight.check_navigation(msgspec.structs.replace(goal, max_turn_rate=0.5), START)
    for command in (
        lambda: tight.check_navigation(msgspec.structs.replace(goal, max_speed=0.3 + EPS), START),
        lambda: tight.check_navigation(msgspec.structs.replace(goal, max_turn_rate=0.5 + EPS), START),
        lambda: tight.check_cmd_vel(Twist(linear_x=0.3 + EPS), START),
        lambda: tight.check_cmd_vel(Twist(angular_z=0.5 + EPS), START),
    ):
        with pytest.raises(Vetoed) as refused:
            command()
        assert refused.value.rule is Rule.BASE_SPEED
    assert tight.check_cmd_vel(Twist(linear_x=0.3, angular_z=-0.5), START)
    assert tight.check_gripper(GripperCommandGoal(position=0.0, max_effort=20.0))
    with pytest.raises(Vetoed, match="exceeds the limit of 20 N"):
        tight.check_gripper(GripperCommandGoal(position=0.0, max_effort=20.0 + EPS))
    # The gripper lets anything over the tightened payload slip, and may not be told otherwise.
    assert tight.check_gripper(GripperCommandGoal(position=0.0, max_effort=10.0)).command.payload_limit == 1.0
    with pytest.raises(Vetoed, match="exceeds the arm's payload of 1 kg") as heavier:
        tight.check_gripper(GripperCommandGoal(position=0.0, max_effort=10.0, payload_limit=1.0 + EPS))
    assert heavier.value.rule is Rule.PAYLOAD


def test_a_policys_own_keep_out_zone_is_enforced_like_the_worlds(tmp_path: Path, arm: ArmModel) -> None:
    path = tmp_path / "policy.toml"
    path.write_bytes(
        DEFAULT_BYTES
        + b'\n[[keep_out]]\nid = "nursery"\nname = "nursery"\nreason = "the baby is asleep"\n'
        + b"polygon = [[1.0, 6.0], [3.0, 6.0], [3.0, 8.0], [1.0, 8.0]]\n"
    )
    limits = load(path, arm)
    assert [zone.id for zone in limits.keep_out] == ["stairs", "nursery"]
    with_nursery, without = checks(limits, arm, OPEN_FLOOR), checks(load(None, arm), arm, OPEN_FLOOR)
    # Approaching the nursery's east edge from the east: a footprint (half-diagonal) away or closer.
    start = Pose2D(x=3.8, y=5.5)
    clear = NavigateToPoseGoal(pose=Pose2D(x=3.0 + RADIUS + EPS, y=7.0, yaw=math.pi))
    assert with_nursery.check_navigation(clear, start).command.pose == clear.pose
    close = NavigateToPoseGoal(pose=Pose2D(x=3.0 + RADIUS - EPS, y=7.0, yaw=math.pi))
    assert without.check_navigation(close, start).command.pose == close.pose
    with pytest.raises(Vetoed, match="keep-out zone 'nursery': the baby is asleep") as refused:
        with_nursery.check_navigation(close, start)
    assert refused.value.rule is Rule.KEEP_OUT
    # Driving through it, the monitors finding the base in it, the arm reaching into it.
    through = NavigateToPoseGoal(pose=Pose2D(x=0.1, y=7.0, yaw=math.pi))
    assert without.check_navigation(through, Pose2D(x=3.6, y=7.0)).command.pose == through.pose
    with pytest.raises(Vetoed) as crossing:
        with_nursery.check_navigation(through, Pose2D(x=3.6, y=7.0))
    assert crossing.value.rule is Rule.KEEP_OUT
    assert str(crossing.value) == (
        "path from (3.60, 7.00) to (0.50, 7.00) takes the base's footprint into keep-out zone 'nursery': "
        "the baby is asleep"
    )
    assert without.zone_at(2.0, 7.0) is None
    zone = with_nursery.zone_at(2.0, 7.0)
    assert zone is not None and zone.id == "nursery"
    with pytest.raises(Vetoed) as reached:
        with_nursery.check_cmd_vel(Twist(linear_x=0.5), Pose2D(x=3.0 + RADIUS + 0.4, y=7.0, yaw=math.pi))
    assert reached.value.rule is Rule.CMD_VEL_HORIZON
