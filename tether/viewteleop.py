"""Teleop from Foxglove's Teleop panel through `tether view`: which client channels are taken, what a
message becomes, and the deadman. Pure: the time comes in as an argument, nothing here touches
Zenoh or the WebSocket server (tether/view.py binds it to both).

The Teleop panel advertises one client channel (schema geometry_msgs/Twist, JSON encoded when the
server offers "json") on the topic set in its settings, and while a button is held sends the same
twist at its publish rate. Each accepted message becomes a tether Twist for cmd/teleop/cmd_vel,
where safety clamps it as it clamps `tether teleop`. The deadman: no message for DEADMAN seconds,
or the sending channel gone (unadvertised, its client disconnected), and the robot is told to stop.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import msgspec

from schemas.common import DECODE_ERRORS
from schemas.robot import Twist

# The one topic a Foxglove client may publish on (the Teleop panel's default, set in
# deploy/foxglove-layout.json); any other is refused.
TELEOP_TOPIC = "/cmd_vel"
# ROS 1 and ROS 2 spellings: the panel names ROS 1's, other clients may name ROS 2's.
TWIST_SCHEMAS = frozenset({"geometry_msgs/Twist", "geometry_msgs/msg/Twist"})
ENCODING = "json"
# Seconds without a message before the view tells the robot to stop (the panel repeats a held
# button at its publish rate: at least 3 Hz keeps the robot going; the layout sets 10 Hz).
DEADMAN = 0.5
# Per client: messages a second, and how many may come at once (a burst after a network hiccup).
RATE_HZ = 50.0
BURST = 10
# Client channels taken on the teleop topic, per client and in all; more are refused.
MAX_CHANNELS_PER_CLIENT = 4
MAX_CHANNELS = 32
# A Twist in JSON is about 80 bytes; anything much bigger is not one.
MAX_MESSAGE_BYTES = 2048
# tether's Twist carries at most this (schemas.robot's bounds); safety clamps what is within it to
# the robot's limits and reports it, what is beyond it is refused here.
MAX_VALUE = 100.0
# The axes a ground robot has; the others of a geometry_msgs/Twist are ignored (with one warning).
USED_AXES = ("linear.x", "angular.z")
IGNORED_AXES = ("linear.y", "linear.z", "angular.x", "angular.y")


class Refused(Exception):
    """A client's advertisement or message not taken; the message says why, the class what kind of
    problem it is (for logging each kind apart)."""


class BadChannel(Refused):
    """An advertisement of a channel that is not a JSON Twist on the teleop topic, or one too many."""


class UnknownChannel(Refused):
    """A message on a channel not taken."""


class RateLimited(Refused):
    """A message over its client's rate: dropped and counted."""


class BadMessage(Refused):
    """A message that is not a sane Twist."""


class Rearming(Refused):
    """A twist after safety's e-stop latched, before every panel let go of its buttons since."""


class Vector3(msgspec.Struct):
    x: float = 0.0
    y: float = 0.0
    z: float = 0.0


class RosTwist(msgspec.Struct):
    """geometry_msgs/Twist as Foxglove encodes it in JSON; a missing part is zero."""

    linear: Vector3 = msgspec.field(default_factory=Vector3)
    angular: Vector3 = msgspec.field(default_factory=Vector3)


_decoder = msgspec.json.Decoder(RosTwist)


def check_channel(topic: str, encoding: str, schema_name: str) -> None:
    """Raise Refused unless this is a Twist in JSON on the teleop topic."""
    if topic != TELEOP_TOPIC:
        raise BadChannel(f"topic {topic[:80]!r}: teleop is taken on {TELEOP_TOPIC!r} only")
    if encoding != ENCODING:
        raise BadChannel(f"encoding {encoding[:40]!r}: teleop is taken in {ENCODING!r} only")
    if schema_name not in TWIST_SCHEMAS:
        raise BadChannel(f"schema {schema_name[:80]!r}: teleop takes geometry_msgs/Twist only")


def to_twist(data: bytes) -> tuple[Twist, list[str]]:
    """A JSON geometry_msgs/Twist as tether's Twist (stamp 0), and the ignored axes that were not zero.

    Raises BadMessage for anything else: not JSON, not a Twist, a value not finite or beyond MAX_VALUE."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise BadMessage(f"{len(data)} bytes: a geometry_msgs/Twist in JSON is under {MAX_MESSAGE_BYTES}")
    try:
        ros = _decoder.decode(data)
    except (*DECODE_ERRORS, msgspec.ValidationError) as exc:
        raise BadMessage(f"not a geometry_msgs/Twist in JSON: {exc}") from None
    values = {
        "linear.x": ros.linear.x,
        "linear.y": ros.linear.y,
        "linear.z": ros.linear.z,
        "angular.x": ros.angular.x,
        "angular.y": ros.angular.y,
        "angular.z": ros.angular.z,
    }
    for name, value in values.items():
        if not math.isfinite(value):
            raise BadMessage(f"{name} is {value}")
        if abs(value) > MAX_VALUE:
            raise BadMessage(f"{name} is {value:g}, beyond +-{MAX_VALUE:g}")
    ignored = [name for name in IGNORED_AXES if values[name] != 0.0]
    return Twist(linear_x=values["linear.x"], angular_z=values["angular.z"]), ignored


@dataclass
class Bucket:
    """A token bucket: `rate` a second, at most `burst` saved up."""

    rate: float = RATE_HZ
    burst: float = BURST
    tokens: float = BURST
    at: float = -math.inf

    def take(self, now: float) -> bool:
        if self.at != -math.inf:
            self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    def full_by(self, now: float) -> bool:
        """Whether it has saved up `burst` again by `now`: then it is as good as a new one."""
        if self.at == -math.inf:
            return self.tokens >= self.burst
        return self.tokens + max(0.0, now - self.at) * self.rate >= self.burst


@dataclass(frozen=True)
class Accepted:
    """A message taken: the twist to send, and the ignored axes to warn about (each once per view)."""

    twist: Twist
    warn_ignored: list[str] = field(default_factory=list)


class TeleopGate:
    """Client channels, messages and the deadman, for all clients of one view. Thread-safe: the
    server's callbacks and the deadman's thread call it. Each method that may stop the robot returns
    the stop (a zero Twist) for the caller to send, or None."""

    def __init__(self, deadman: float = DEADMAN, rate: float = RATE_HZ, burst: int = BURST) -> None:
        self.deadman = deadman
        self._rate, self._burst = rate, float(burst)
        self._lock = threading.Lock()
        self._channels: set[tuple[int, int]] = set()  # (client id, client channel id) taken
        # A client's bucket outlives its channels: advertising again must not refill it. It goes
        # once the client has no channel and the bucket has saved up its burst again (a new one
        # would be the same), as of the latest message's time: clients coming and going leave none.
        self._buckets: dict[int, Bucket] = {}
        self._idle: set[int] = set()  # clients with a bucket and no channel
        self._now = -math.inf  # the time of the latest message
        self._driver: tuple[int, int] | None = None  # the channel of the last twist sent
        self._last = -math.inf  # when it came
        self._moving = False  # the last twist sent was not a stop
        # Once safety's e-stop latched, twists move nothing until no message has come for `deadman`
        # seconds with the e-stop clear: a `tether reset` does not set the robot off on a panel's
        # button still held (its messages keep coming while it is).
        self._latched = False
        self._rearming = False
        self._held_at = -math.inf  # the latest message while rearming
        self._warned: set[str] = set()
        self.accepted = 0
        self.refused = 0
        self.rate_dropped = 0
        self.stops = 0

    def advertise(self, client: int, channel: int, topic: str, encoding: str, schema_name: str) -> None:
        """Take a client channel, or raise Refused."""
        with self._lock:
            try:
                check_channel(topic, encoding, schema_name)
                mine = sum(1 for c, _ in self._channels if c == client)
                if mine >= MAX_CHANNELS_PER_CLIENT:
                    raise BadChannel(f"client has {mine} teleop channels already (at most {MAX_CHANNELS_PER_CLIENT})")
                if len(self._channels) >= MAX_CHANNELS:
                    raise BadChannel(f"{len(self._channels)} teleop channels are open (at most {MAX_CHANNELS})")
            except Refused:
                self.refused += 1
                raise
            self._channels.add((client, channel))
            self._idle.discard(client)
            self._buckets.setdefault(client, Bucket(self._rate, self._burst, self._burst))

    def message(self, client: int, channel: int, data: bytes, now: float) -> Accepted:
        """The twist of one message, or raise Refused (RateLimited over the client's rate)."""
        with self._lock:
            self._now = max(self._now, now)
            self._forget_full_buckets()
            try:
                if (client, channel) not in self._channels:
                    raise UnknownChannel(f"channel {channel} was not taken (advertise {TELEOP_TOPIC!r} first)")
                if not self._buckets[client].take(now):
                    self.rate_dropped += 1
                    raise RateLimited(f"more than {self._rate:g} messages a second from this client: dropped")
                twist, ignored = to_twist(data)
                if self._rearming:
                    self._held_at = now
                    raise Rearming(
                        "the e-stop latched: let go of the teleop panel's buttons, then drive"
                        if self._latched
                        else "the e-stop was reset: let go of the teleop panel's buttons, then drive"
                    )
            except Refused:
                self.refused += 1
                raise
            self.accepted += 1
            self._driver, self._last = (client, channel), now
            self._moving = twist.linear_x != 0.0 or twist.angular_z != 0.0
            new = [axis for axis in ignored if axis not in self._warned]
            self._warned.update(new)
            return Accepted(twist, new)

    def _stop(self) -> Twist:
        self._moving = False
        self.stops += 1
        return Twist()

    def unadvertise(self, client: int, channel: int) -> Twist | None:
        """A channel gone: if it was driving, stop now."""
        with self._lock:
            self._channels.discard((client, channel))
            if client in self._buckets and not any(c == client for c, _ in self._channels):
                self._idle.add(client)
                self._forget_full_buckets()
            if self._moving and self._driver == (client, channel):
                return self._stop()
            return None

    def _forget_full_buckets(self) -> None:
        for client in [c for c in self._idle if self._buckets[c].full_by(self._now)]:
            del self._buckets[client]
            self._idle.discard(client)

    def expire(self, now: float) -> Twist | None:
        """The deadman: the stop once no message has come for `deadman` seconds while moving."""
        with self._lock:
            if self._rearming and not self._latched and now - self._held_at >= self.deadman:
                self._rearming = False
            if self._moving and now - self._last >= self.deadman:
                return self._stop()
            return None

    def estop(self, latched: bool) -> Twist | None:
        """What safety's heartbeat says of its e-stop; latched, the stop if the robot was driven."""
        with self._lock:
            self._latched = latched
            if not latched:
                return None
            self._rearming = True
            return self._stop() if self._moving else None

    @property
    def rearming(self) -> bool:
        with self._lock:
            return self._rearming

    @property
    def moving(self) -> bool:
        with self._lock:
            return self._moving

    @property
    def channels(self) -> int:
        with self._lock:
            return len(self._channels)
