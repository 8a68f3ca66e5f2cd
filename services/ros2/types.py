"""ROS 2 types without ROS 2: rosbags' typestore plus our bundled interfaces, CDR and RIHS01 hashes."""

from __future__ import annotations

import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype
from rosbags.typesys.store import Typestore

INTERFACES = Path(__file__).parent / "interfaces"

DISTROS = {
    "humble": Stores.ROS2_HUMBLE,
    "iron": Stores.ROS2_IRON,
    "jazzy": Stores.ROS2_JAZZY,
    "kilted": Stores.ROS2_KILTED,
}

# Little-endian plain CDR, the only representation rmw_zenoh and rosbags write.
CDR_HEADER = b"\x00\x01\x00\x00"

_UUID = (Nodetype.NAME, "unique_identifier_msgs/msg/UUID")
_TIME = (Nodetype.NAME, "builtin_interfaces/msg/Time")

_ZERO = {
    "bool": False,
    "string": "",
    "wstring": "",
    "float32": 0.0,
    "float64": 0.0,
}

_NUMPY_DTYPES = {
    "bool": "bool",
    "byte": "uint8",
    "char": "uint8",
    "int8": "int8",
    "uint8": "uint8",
    "int16": "int16",
    "uint16": "uint16",
    "int32": "int32",
    "uint32": "uint32",
    "int64": "int64",
    "uint64": "uint64",
    "float32": "float32",
    "float64": "float64",
}

Typesdict = dict[str, tuple[list[Any], list[Any]]]

# Default values from .msg files that rosbags' typestores drop and that matter: an unset orientation
# is the identity rotation, as in rclpy and rclcpp, never the invalid zero quaternion.
_DEFAULTS: dict[str, dict[str, Any]] = {"geometry_msgs/msg/Quaternion": {"w": 1.0}}


class _HashView:
    """The typestore's definitions as rosidl hashes them: a .msg `char` is rosidl's uint8.

    rosbags hashes `char` as FIELD_TYPE_CHAR (13); rosidl maps the .msg `char` to IDL uint8 (3) before
    hashing, so every type holding service_msgs/ServiceEventInfo (char[16] client_gid), i.e. every
    service, would get a hash no ROS 2 node uses. Only the hash sees this view; CDR is unchanged.
    """

    def __init__(self, fielddefs: Typesdict) -> None:
        self.fielddefs = _CharAsUint8(fielddefs)


class _CharAsUint8(dict[str, Any]):
    def __init__(self, fielddefs: Typesdict) -> None:
        super().__init__()
        self._source = fielddefs

    def __getitem__(self, ros_type: str) -> Any:
        consts, fields = self._source[ros_type]
        return consts, [(name, _char_as_uint8(desc)) for name, desc in fields]

    def __contains__(self, ros_type: object) -> bool:
        return ros_type in self._source


def _char_as_uint8(desc: Any) -> Any:
    kind, rest = desc
    if kind == Nodetype.BASE:
        return (kind, ("uint8", rest[1])) if rest[0] == "char" else desc
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        sub, count = rest
        return (kind, (_char_as_uint8(sub), count))
    return desc


def _as_msg(ros_type: str) -> str:
    pkg, _, name = ros_type.split("/", 2)
    return f"{pkg}/msg/{name}"


def _refs_as_msg(typedef: Any) -> Any:
    consts, fields = typedef
    return consts, [(name, _desc_as_msg(desc)) for name, desc in fields]


def _desc_as_msg(desc: Any) -> Any:
    kind, rest = desc
    if kind == Nodetype.NAME:
        return (kind, _as_msg(rest))
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        sub, count = rest
        return (kind, (_desc_as_msg(sub), count))
    return desc


# rosbags' own RIHS01 algorithm, applied to the view above.
_HASHER = Typestore.hash_rihs01


class RosDecodeError(Exception):
    """Bytes that are not a valid CDR encoding of the expected ROS 2 type."""


class RosTypeError(Exception):
    """A ROS 2 type we do not know, or a message that does not fit its type."""


def _split_sections(text: str, path: Path, count: int) -> list[str]:
    sections: list[list[str]] = [[]]
    for line in text.splitlines():
        if line.strip() == "---":
            sections.append([])
        else:
            sections[-1].append(line)
    if len(sections) != count:
        raise RosTypeError(f"{path}: expected {count} sections separated by '---', found {len(sections)}")
    return ["\n".join(lines) + "\n" for lines in sections]


def _parse(text: str, pkg: str, name: str) -> tuple[list[Any], list[Any]]:
    """One message section; relative type names resolve inside `pkg`'s msg folder, as rosidl does."""
    parsed = get_types_from_msg(text, f"{pkg}/msg/{name}")
    consts, fields = parsed[f"{pkg}/msg/{name}"]
    return list(consts), list(fields)


def _name(ros_type: str) -> tuple[Nodetype, str]:
    return (Nodetype.NAME, ros_type)


def _bounded1(ros_type: str) -> tuple[Nodetype, tuple[tuple[Nodetype, str], int]]:
    return (Nodetype.SEQUENCE, (_name(ros_type), 1))


Typedef = tuple[list[Any], list[Any]]


def service_types(srv_type: str, request: Typedef, response: Typedef) -> Typesdict:
    """The message types rosidl generates for a service: Request, Response, Event and the service itself.

    The service's own entry has the fields of its type description (request_message, response_message,
    event_message), so its RIHS01 hash is the one rmw_zenoh puts on the service's key.
    """
    event_info = (Nodetype.NAME, "service_msgs/msg/ServiceEventInfo")
    return {
        f"{srv_type}_Request": request,
        f"{srv_type}_Response": response,
        f"{srv_type}_Event": (
            [],
            [
                ("info", event_info),
                ("request", _bounded1(f"{srv_type}_Request")),
                ("response", _bounded1(f"{srv_type}_Response")),
            ],
        ),
        srv_type: (
            [],
            [
                ("request_message", _name(f"{srv_type}_Request")),
                ("response_message", _name(f"{srv_type}_Response")),
                ("event_message", _name(f"{srv_type}_Event")),
            ],
        ),
    }


def action_types(action_type: str, goal: Any, result: Any, feedback: Any) -> Typesdict:
    """The types rosidl generates for an action: Goal, Result, Feedback, the SendGoal and GetResult
    services, FeedbackMessage, and the action's own type description."""
    types: Typesdict = {
        f"{action_type}_Goal": goal,
        f"{action_type}_Result": result,
        f"{action_type}_Feedback": feedback,
        f"{action_type}_FeedbackMessage": (
            [],
            [("goal_id", _UUID), ("feedback", _name(f"{action_type}_Feedback"))],
        ),
    }
    types |= service_types(
        f"{action_type}_SendGoal",
        ([], [("goal_id", _UUID), ("goal", _name(f"{action_type}_Goal"))]),
        ([], [("accepted", (Nodetype.BASE, ("bool", 0))), ("stamp", _TIME)]),
    )
    types |= service_types(
        f"{action_type}_GetResult",
        ([], [("goal_id", _UUID)]),
        ([], [("status", (Nodetype.BASE, ("int8", 0))), ("result", _name(f"{action_type}_Result"))]),
    )
    types[action_type] = (
        [],
        [
            ("goal", _name(f"{action_type}_Goal")),
            ("result", _name(f"{action_type}_Result")),
            ("feedback", _name(f"{action_type}_Feedback")),
            ("send_goal_service", _name(f"{action_type}_SendGoal")),
            ("get_result_service", _name(f"{action_type}_GetResult")),
            ("feedback_message", _name(f"{action_type}_FeedbackMessage")),
        ],
    )
    return types


def load_interfaces(root: Path = INTERFACES) -> Typesdict:
    """Every .msg, .srv and .action under root/<pkg>/<kind>/, expanded the way rosidl expands them."""
    types: Typesdict = {}
    for path in sorted(root.glob("*/*/*")):
        pkg, kind, name = path.parent.parent.name, path.parent.name, path.stem
        text = path.read_text()
        if path.suffix == ".msg" and kind == "msg":
            types[f"{pkg}/msg/{name}"] = _parse(text, pkg, name)
        elif path.suffix == ".srv" and kind == "srv":
            request, response = _split_sections(text, path, 2)
            types |= service_types(
                f"{pkg}/srv/{name}",
                _parse(request, pkg, f"{name}_Request"),
                _parse(response, pkg, f"{name}_Response"),
            )
        elif path.suffix == ".action" and kind == "action":
            goal, result, feedback = _split_sections(text, path, 3)
            types |= action_types(
                f"{pkg}/action/{name}",
                _parse(goal, pkg, f"{name}_Goal"),
                _parse(result, pkg, f"{name}_Result"),
                _parse(feedback, pkg, f"{name}_Feedback"),
            )
    return types


def _coerce(ros_type: str, name: str, desc: Any, value: Any) -> Any:
    """Numbers in arrays and sequences as the numpy arrays rosbags encodes; lists, tuples, bytes welcome."""
    import numpy as np

    kind, rest = desc
    if kind not in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return value
    (sub_kind, sub_rest), count = rest
    if sub_kind != Nodetype.BASE or sub_rest[0] not in _NUMPY_DTYPES:
        return value
    dtype = _NUMPY_DTYPES[sub_rest[0]]
    if isinstance(value, bytes | bytearray | memoryview):
        array = np.frombuffer(bytes(value), dtype=np.uint8).astype(dtype)
    else:
        try:
            array = np.asarray(value, dtype=dtype)
        except (TypeError, ValueError) as exc:
            raise RosTypeError(f"{ros_type}.{name} takes {sub_rest[0]} numbers: {exc}") from exc
    if array.ndim != 1:
        raise RosTypeError(f"{ros_type}.{name} takes a flat list of {sub_rest[0]}, got shape {array.shape}")
    if kind == Nodetype.ARRAY and len(array) != count:
        raise RosTypeError(f"{ros_type}.{name} takes exactly {count} values, got {len(array)}")
    if kind == Nodetype.SEQUENCE and count and len(array) > count:
        raise RosTypeError(f"{ros_type}.{name} takes at most {count} values, got {len(array)}")
    return array


class RosTypes:
    """One rosbags typestore for a ROS 2 distribution plus our bundled interfaces.

    Encoding, decoding and hashing are rosbags'; this class adds the service and action types rosidl
    generates (rosbags ships messages only) and turns every failure into RosDecodeError or RosTypeError.
    """

    def __init__(self, distro: str = "jazzy", *, interfaces: Sequence[Path] = ()) -> None:
        """`interfaces`: more folders laid out like services/ros2/interfaces (<pkg>/msg|srv|action/<Name>)."""
        if distro not in DISTROS:
            raise RosTypeError(f"unknown ROS 2 distribution {distro!r}; known: {', '.join(DISTROS)}")
        self.distro = distro
        self._store = get_typestore(DISTROS[distro])
        bundled: Typesdict = {}
        for root in (INTERFACES, *interfaces):
            bundled |= load_interfaces(Path(root))
        try:
            self._store.register({k: v for k, v in bundled.items() if k not in self._store.fielddefs})
        except Exception as exc:  # a definition referring to a type nobody defines, or a clash
            raise RosTypeError(f"cannot load interface definitions: {exc}") from exc
        self._hashes: dict[str, str] = {}
        self._msg_view: Typestore | None = None
        self._lock = threading.Lock()

    def known(self, ros_type: str) -> bool:
        return ros_type in self._store.fielddefs

    def _check(self, ros_type: str) -> None:
        if ros_type not in self._store.fielddefs:
            raise RosTypeError(f"unknown ROS 2 type {ros_type!r} (distribution {self.distro})")

    def hash(self, ros_type: str) -> str:
        """RIHS01 hash of a message, service or action type, as rosidl computes it."""
        with self._lock:
            if cached := self._hashes.get(ros_type):
                return cached
        self._check(ros_type)
        digest = _HASHER(cast(Typestore, _HashView(self._store.fielddefs)), ros_type)
        with self._lock:
            self._hashes[ros_type] = digest
        return digest

    def encode(self, ros_type: str, message: object) -> bytes:
        """CDR bytes (little endian, header 00 01 00 00) of a message of this type."""
        self._check(ros_type)
        try:
            return bytes(self._store.serialize_cdr(message, ros_type))
        except Exception as exc:  # rosbags raises whatever struct/attribute error the bad field causes
            raise RosTypeError(f"cannot encode {type(message).__name__} as {ros_type}: {exc}") from exc

    def decode(self, ros_type: str, data: bytes) -> Any:
        """The message CDR bytes hold; RosDecodeError saying what is wrong when they hold none."""
        self._check(ros_type)
        if len(data) < 4:
            raise RosDecodeError(f"{ros_type}: {len(data)} bytes, too short for a CDR header")
        if bytes(data[:2]) != CDR_HEADER[:2]:
            raise RosDecodeError(
                f"{ros_type}: CDR header {bytes(data[:4]).hex()} is not little-endian plain CDR (00010000)"
            )
        try:
            return self._store.deserialize_cdr(data, ros_type)
        except Exception as exc:  # truncated, overlong or garbled data: any of struct, index, unicode errors
            reason = str(exc) or type(exc).__name__
            raise RosDecodeError(f"{ros_type}: undecodable CDR ({len(data)} bytes): {reason}") from exc

    def new(self, ros_type: str, **fields: Any) -> Any:
        """A message with the given fields; every other field zero, empty or zero-filled (recursively),
        but for the .msg defaults in _DEFAULTS (a quaternion's w is 1). Numeric arrays and sequences may
        be given as lists, tuples or bytes."""
        self._check(ros_type)
        consts, defs = self._store.fielddefs[ros_type]
        del consts
        names = {name for name, _ in defs}
        if unknown := set(fields) - names:
            raise RosTypeError(f"{ros_type} has no field {', '.join(sorted(unknown))}; fields: {', '.join(names)}")
        fields = {**_DEFAULTS.get(ros_type, {}), **fields}
        values = {
            name: _coerce(ros_type, name, desc, fields[name]) if name in fields else self._zero(desc)
            for name, desc in defs
        }
        return self._store.types[ros_type](**values)

    def _zero(self, desc: Any) -> Any:
        import numpy as np

        kind, rest = desc
        if kind == Nodetype.BASE:
            base = rest[0]
            return _ZERO.get(base, 0)
        if kind == Nodetype.NAME:
            return self.new(rest, **_DEFAULTS.get(rest, {}))
        (sub_kind, sub_rest), count = rest
        if kind == Nodetype.ARRAY:
            if sub_kind == Nodetype.BASE and sub_rest[0] in _NUMPY_DTYPES:
                return np.zeros(count, dtype=_NUMPY_DTYPES[sub_rest[0]])
            return [self._zero((sub_kind, sub_rest)) for _ in range(count)]
        if sub_kind == Nodetype.BASE and sub_rest[0] in _NUMPY_DTYPES:
            return np.zeros(0, dtype=_NUMPY_DTYPES[sub_rest[0]])
        return []

    def fields(self, ros_type: str) -> list[str]:
        """Field names of a type, in order."""
        self._check(ros_type)
        return [name for name, _ in self._store.fielddefs[ros_type][1]]

    def msgdef(self, ros_type: str) -> str:
        """The ros2msg schema text (MCAP's ros2 profile): the type, then each dependency after a MSG: line.

        Types are written `pkg/Name` as rosbag2 and Foxglove read them, also the srv and action ones
        (`nav2_msgs/NavigateToPose_Feedback`), which rosbags' generator refuses, so it sees them as msgs.
        """
        self._check(ros_type)
        with self._lock:
            if self._msg_view is None:
                view = Typestore.__new__(Typestore)
                view.fielddefs = {
                    _as_msg(name): _refs_as_msg(typedef) for name, typedef in self._store.fielddefs.items()
                }
                view.types = {}
                self._msg_view = view
            view = self._msg_view
        text, _ = view.generate_msgdef(_as_msg(ros_type), ros_version=2)
        return text
