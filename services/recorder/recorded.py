"""The world and the safety policy a recording was made with, rebuilt from the files it carries."""

from __future__ import annotations

from pathlib import Path, PurePosixPath

from schemas.world import World
from services.recorder.mcapfile import METADATA_NAME, POLICY_ATTACHMENT, WORLD_ATTACHMENT
from services.recorder.reader import RecordingError, RecordingFile
from services.safety.policy import SafetyPolicy, load_safety_policy
from services.safety.policyfile import PolicyError
from services.worldmodel import WorldFileError, parse_world


def no_file(recording: RecordingFile, kind: str) -> str:
    """Why `recording` gives no `kind` file ("world" or "policy"): recorded without one, or the one its
    metadata names is not in it whole (its record damaged)."""
    named = recording.metadata.get(METADATA_NAME, {}).get(kind)
    if named:
        return f"carries no {kind} file it can read: the {named!r} its metadata names is missing or damaged"
    return f"carries no {kind} file (recorded without one)"


def recorded_world(recording: RecordingFile) -> World:
    """The world file kept in the recording; RecordingError if there is none or it does not load."""
    attachment = recording.world
    if attachment is None:
        raise RecordingError(f"{recording.path} {no_file(recording, WORLD_ATTACHMENT)}")
    try:
        world = parse_world(attachment.data, Path(attachment.name))
    except WorldFileError as exc:
        raise RecordingError(f"{recording.path}: the recorded world does not load: {exc}") from None
    # The world names the arm's URDF, which is then read: a file's world may only name one that
    # ships with pybullet, never a path anywhere on this machine.
    urdf = PurePosixPath(world.robot.arm_urdf)
    if urdf.is_absolute() or ".." in urdf.parts or "\\" in world.robot.arm_urdf:
        raise RecordingError(
            f"{recording.path}: the recorded world's robot.arm_urdf {world.robot.arm_urdf!r} is not a "
            "path inside pybullet_data; a recording may only name the URDFs that ship with it"
        )
    return world


def recorded_policy(
    recording: RecordingFile, world: World, policy: Path | None = None, world_label: str = "the recorded world"
) -> SafetyPolicy:
    """Safety's checks under the policy file kept in the recording, or under `policy` when given;
    `world_label` names `world` in errors."""
    try:
        if policy is not None:
            return load_safety_policy(world, policy, world_label)
        attachment = recording.policy
        if attachment is None:
            raise RecordingError(f"{recording.path} {no_file(recording, POLICY_ATTACHMENT)}; give one with --policy")
        return load_safety_policy(world, Path(attachment.name), world_label, data=attachment.data)
    except PolicyError as exc:
        raise RecordingError(str(exc)) from None
