"""rmw_zenoh's wire format, pure: key expressions, the sample attachment and liveliness tokens."""

from __future__ import annotations

import hashlib
import re
import struct
from dataclasses import dataclass
from enum import IntEnum, StrEnum
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from services.ros2.types import RosTypes

ADMIN_SPACE = "@ros2_lv"
GID_SIZE = 16  # RMW_GID_STORAGE_SIZE since Iron; Humble's 24 has no rmw_zenoh hash keys anyway
ATTACHMENT_SIZE = 8 + 8 + 1 + GID_SIZE
RMW_ZENOH_DEFAULT_DEPTH = 42

CANCEL_GOAL_TYPE = "action_msgs/srv/CancelGoal"
GOAL_STATUS_ARRAY_TYPE = "action_msgs/msg/GoalStatusArray"

_ROS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)$")
_DDS_TYPE = re.compile(r"^([A-Za-z][A-Za-z0-9_]*)::(msg|srv|action)::dds_::([A-Za-z][A-Za-z0-9_]*)_$")
_HASH = re.compile(r"^RIHS01_[0-9a-f]{64}$")


class Style(StrEnum):
    RMW_ZENOH = "rmw_zenoh"  # <domain>/<name>/<dds type>/<RIHS01 hash>, attachment on every sample
    BRIDGE = "bridge"  # zenoh-bridge-ros2dds: the bare name, no attachment


class GoalStatus(IntEnum):
    """action_msgs/msg/GoalStatus codes."""

    UNKNOWN = 0
    ACCEPTED = 1
    EXECUTING = 2
    CANCELING = 3
    SUCCEEDED = 4
    CANCELED = 5
    ABORTED = 6

    @property
    def terminal(self) -> bool:
        return self >= GoalStatus.SUCCEEDED


class CancelReturn(IntEnum):
    """action_msgs/srv/CancelGoal response return codes."""

    ERROR_NONE = 0
    ERROR_REJECTED = 1
    ERROR_UNKNOWN_GOAL_ID = 2
    ERROR_GOAL_TERMINATED = 3


class EntityKind(StrEnum):
    NODE = "NN"
    PUBLISHER = "MP"
    SUBSCRIPTION = "MS"
    SERVICE = "SS"
    CLIENT = "SC"


def dds_type(ros_type: str) -> str:
    """`geometry_msgs/msg/Twist` -> `geometry_msgs::msg::dds_::Twist_`, the type chunk of rmw_zenoh keys."""
    match = _ROS_TYPE.match(ros_type)
    if match is None:
        raise ValueError(f"not a ROS 2 type name (pkg/msg|srv|action/Name): {ros_type!r}")
    pkg, kind, name = match.groups()
    return f"{pkg}::{kind}::dds_::{name}_"


def ros_type_of(dds: str) -> str | None:
    """The inverse of dds_type; None for anything else."""
    match = _DDS_TYPE.match(dds)
    if match is None:
        return None
    pkg, kind, name = match.groups()
    return f"{pkg}/{kind}/{name}"


def qualify(name: str, namespace: str = "") -> str:
    """The fully qualified ROS name: `cmd_vel` in `/robot1` -> `/robot1/cmd_vel`; absolute names stay."""
    if name.startswith("/"):
        full = name
    else:
        ns = namespace.strip("/")
        full = f"/{ns}/{name}" if ns else f"/{name}"
    full = full.rstrip("/") or "/"
    if "//" in full or full == "/" or any(not part for part in full[1:].split("/")):
        raise ValueError(f"not a valid ROS name: {name!r} (namespace {namespace!r})")
    return full


def mangle(name: str) -> str:
    """rmw_zenoh's liveliness mangling: every '/' becomes '%'."""
    return name.replace("/", "%")


@dataclass(frozen=True)
class Qos:
    """The QoS a liveliness token advertises; rmw_zenoh writes only what differs from the default."""

    reliable: bool = True
    transient_local: bool = False
    depth: int = 10

    def keyexpr(self) -> str:
        # <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>
        # with each part empty when it equals rmw_zenoh's default (detail/qos.cpp): reliable, volatile,
        # keep_last, depth 42 (0 means that too), infinite deadline, lifespan and lease, automatic.
        reliability = "" if self.reliable else "2"
        durability = "1" if self.transient_local else ""
        depth = "" if self.depth in (0, RMW_ZENOH_DEFAULT_DEPTH) else str(self.depth)
        return f"{reliability}:{durability}:,{depth}:,:,:,,"


DEFAULT_QOS = Qos()  # rclcpp's default: reliable, volatile, keep_last 10
SERVICE_QOS = Qos()  # rmw_qos_profile_services_default: the same
STATUS_QOS = Qos(transient_local=True, depth=1)  # rcl_action_qos_profile_status_default
SENSOR_QOS = Qos(reliable=False, depth=5)  # rmw_qos_profile_sensor_data


@dataclass(frozen=True)
class Endpoint:
    """One topic or service on the wire: its fully qualified name, type, hash and key."""

    name: str
    ros_type: str
    type_hash: str
    key: str


@dataclass(frozen=True)
class ActionKeyset:
    """The five endpoints rcl_action builds for an action `<name>`, under `<name>/_action/`."""

    send_goal: Endpoint  # service pkg/action/X_SendGoal
    cancel_goal: Endpoint  # service action_msgs/srv/CancelGoal
    get_result: Endpoint  # service pkg/action/X_GetResult
    feedback: Endpoint  # topic pkg/action/X_FeedbackMessage
    status: Endpoint  # topic action_msgs/msg/GoalStatusArray (transient local)

    def keys(self) -> tuple[str, ...]:
        return (self.send_goal.key, self.cancel_goal.key, self.get_result.key, self.feedback.key, self.status.key)


@dataclass(frozen=True)
class Naming:
    """How ROS names become Zenoh keys in one style, domain and namespace."""

    style: Style
    domain_id: int
    namespace: str = ""

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"ROS domain id must be 0..232, got {self.domain_id}")

    def qualify(self, name: str) -> str:
        return qualify(name, self.namespace)

    def _key(self, name: str, ros_type: str, type_hash: str) -> str:
        stripped = self.qualify(name).strip("/")
        if self.style is Style.BRIDGE:
            return stripped
        if not _HASH.match(type_hash):
            raise ValueError(f"not an RIHS01 type hash: {type_hash!r}")
        return f"{self.domain_id}/{stripped}/{dds_type(ros_type)}/{type_hash}"

    def topic(self, name: str, ros_type: str, type_hash: str) -> str:
        """`0/cmd_vel/geometry_msgs::msg::dds_::Twist_/RIHS01_…` (rmw_zenoh) or `cmd_vel` (bridge)."""
        return self._key(name, ros_type, type_hash)

    def service(self, name: str, srv_type: str, type_hash: str) -> str:
        """A service's queryable key; the hash is the service type's (request, response and event)."""
        return self._key(name, srv_type, type_hash)

    def endpoint(self, name: str, ros_type: str, types: RosTypes) -> Endpoint:
        type_hash = types.hash(ros_type)
        return Endpoint(self.qualify(name), ros_type, type_hash, self._key(name, ros_type, type_hash))

    def action(self, name: str, action_type: str, types: RosTypes) -> ActionKeyset:
        base = self.qualify(name)
        return ActionKeyset(
            send_goal=self.endpoint(f"{base}/_action/send_goal", f"{action_type}_SendGoal", types),
            cancel_goal=self.endpoint(f"{base}/_action/cancel_goal", CANCEL_GOAL_TYPE, types),
            get_result=self.endpoint(f"{base}/_action/get_result", f"{action_type}_GetResult", types),
            feedback=self.endpoint(f"{base}/_action/feedback", f"{action_type}_FeedbackMessage", types),
            status=self.endpoint(f"{base}/_action/status", GOAL_STATUS_ARRAY_TYPE, types),
        )

    def parse(self, key: str) -> tuple[str, str, str] | None:
        """(fully qualified name, ROS type, hash) of an rmw_zenoh key in this domain; None for any other key."""
        parts = str(key).split("/")
        if len(parts) < 4 or parts[0] != str(self.domain_id):
            return None
        ros_type = ros_type_of(parts[-2])
        if ros_type is None or not _HASH.match(parts[-1]) or not all(parts[1:-2]):
            return None
        return "/" + "/".join(parts[1:-2]), ros_type, parts[-1]


@dataclass(frozen=True)
class Attachment:
    """rmw_zenoh's attachment on every publication, query and reply (zenoh-ext serialization, 33 bytes):
    int64 LE sequence number, int64 LE source timestamp (ns since the epoch), LEB128 length 16, GID."""

    sequence_number: int
    source_timestamp: int
    gid: bytes

    def encode(self) -> bytes:
        if len(self.gid) != GID_SIZE:
            raise ValueError(f"GID must be {GID_SIZE} bytes, got {len(self.gid)}")
        return struct.pack("<qq", self.sequence_number, self.source_timestamp) + bytes([GID_SIZE]) + bytes(self.gid)

    @classmethod
    def decode(cls, data: bytes) -> Attachment:
        """The attachment in `data`; also rmw_zenoh_cpp <= 0.2.3's labeled form (77 bytes); else ValueError."""
        data = bytes(data)
        if data.startswith(_LABELED[0]):
            return cls._decode_labeled(data)
        # rmw_zenoh ignores trailing bytes; we refuse them, since nothing valid ever carries any.
        if len(data) != ATTACHMENT_SIZE:
            raise ValueError(f"attachment is {len(data)} bytes, rmw_zenoh's is {ATTACHMENT_SIZE}")
        if data[16] != GID_SIZE:
            raise ValueError(f"attachment GID length byte is {data[16]}, expected {GID_SIZE}")
        sequence_number, source_timestamp = struct.unpack_from("<qq", data)
        if sequence_number < 0 or source_timestamp < 0:
            raise ValueError(f"attachment has negative sequence number {sequence_number} or timestamp")
        return cls(sequence_number, source_timestamp, data[17:])

    @classmethod
    def _decode_labeled(cls, data: bytes) -> Attachment:
        # "sequence_number" <int64> "source_timestamp" <int64> "source_gid" <16 bytes>, each string and
        # the GID slice behind a LEB128 length byte (zenoh-ext serialization, as in the unlabeled form).
        sequence_label, timestamp_label, gid_label = _LABELED
        size = len(sequence_label) + 8 + len(timestamp_label) + 8 + len(gid_label) + 1 + GID_SIZE
        if len(data) != size:
            raise ValueError(f"labeled attachment is {len(data)} bytes, expected {size}")
        at = len(sequence_label)
        (sequence_number,) = struct.unpack_from("<q", data, at)
        at += 8
        if data[at : at + len(timestamp_label)] != timestamp_label:
            raise ValueError("labeled attachment lacks source_timestamp")
        at += len(timestamp_label)
        (source_timestamp,) = struct.unpack_from("<q", data, at)
        at += 8
        if data[at : at + len(gid_label) + 1] != gid_label + bytes([GID_SIZE]):
            raise ValueError("labeled attachment lacks a 16-byte source_gid")
        if sequence_number < 0 or source_timestamp < 0:
            raise ValueError(f"attachment has negative sequence number {sequence_number} or timestamp")
        return cls(sequence_number, source_timestamp, data[-GID_SIZE:])


def _label(text: str) -> bytes:
    return bytes([len(text)]) + text.encode()


_LABELED = (_label("sequence_number"), _label("source_timestamp"), _label("source_gid"))


def entity_gid(token: str) -> bytes:
    """A 16-byte GID derived from an entity's liveliness key, unique as rmw_zenoh's own.

    rmw_zenoh uses XXH3-128 of the same string; peers only compare GIDs for equality, so any
    stable 16-byte digest of it serves (blake2b, from the standard library).
    """
    return hashlib.blake2b(token.encode(), digest_size=GID_SIZE).digest()


def liveliness_token(
    kind: EntityKind,
    *,
    domain_id: int,
    zid: str,
    node_id: int,
    entity_id: int,
    node_name: str,
    namespace: str = "/",
    enclave: str = "/",
    name: str | None = None,
    ros_type: str | None = None,
    type_hash: str | None = None,
    qos: Qos = DEFAULT_QOS,
) -> str:
    """`@ros2_lv/<domain>/<zid>/<nid>/<eid>/<kind>/<enclave>/<namespace>/<node>[/<name>/<type>/<hash>/<qos>]`.

    Names keep their leading '/' and are mangled ('/' -> '%'); the namespace "/" becomes "%". A node's
    token has node_id == entity_id. For services and clients, ros_type is the service type.
    """
    ns = namespace if namespace.startswith("/") else "/" + namespace
    parts = [ADMIN_SPACE, str(domain_id), zid, str(node_id), str(entity_id), kind.value]
    parts += [mangle(enclave), mangle(ns), mangle(node_name)]
    if kind is not EntityKind.NODE:
        if name is None or ros_type is None or type_hash is None:
            raise ValueError(f"a {kind.name.lower()} token needs name, ros_type and type_hash")
        parts += [mangle(name), mangle(dds_type(ros_type)), mangle(type_hash), qos.keyexpr()]
    if any(not part for part in parts):
        raise ValueError(f"empty part in liveliness token {parts}")
    return "/".join(parts)
