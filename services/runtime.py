"""The shared runtime: Zenoh sessions from config, codecs, typed pub/sub/query, liveliness, shutdown."""

from __future__ import annotations

import contextlib
import faulthandler
import functools
import json
import logging
import math
import os
import signal
import threading
import time
import tomllib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar, cast

import msgspec
import zenoh

from schemas import keys
from schemas.common import DECODE_ERRORS, ErrorKind, ServiceError
from schemas.keys import Service, Topic
from schemas.process import ProcessStatus
from schemas.trace import TraceRecord
from services.datafile import read_bounded
from services.errors import CallError
from services.listening import listening_ports
from services.procstat import process_status
from services.querypool import QueryPool
from services.repeats import RepeatLog
from services.robotlink import Refusal, Signer, signed

log = logging.getLogger(__name__)

# Set to 1 in a service's environment to have it declare the bare echo benchmarks compare with.
BENCH_ECHO_ENV = "TETHER_BENCH_ECHO"
# Set to a service's name (safety: "sim") to have this service relay bare bench traffic to that
# service: raw queries to its echo and a raw topic, the baseline for two hops through this process.
BENCH_RELAY_ENV = "TETHER_BENCH_RELAY"
BENCH_RELAY_TIMEOUT = 5.0

T = TypeVar("T")
C = TypeVar("C")
Q = TypeVar("Q")
A = TypeVar("A")

# Every service listens on its own loopback port, base port + offset, and connects to the others,
# so any one of them can restart and find the rest without a router or multicast.
SERVICES = ("sim", "safety", "parser", "resolver", "executor", "recorder", "planner")
# The robot backends besides the sim: "ros2" drives a ROS 2 robot; "ros2sim" is the sim behind a ROS 2
# face, standing in for one on a machine without it (docs/ros2.md).
ROBOT_BACKENDS = {"sim": ("sim",), "ros2": ("ros2",), "ros2-standin": ("ros2", "ros2sim")}
# Every service `tether run` knows; a service's port is the base port plus its index here.
ALL_SERVICES = (*SERVICES, "ros2", "ros2sim")


def stack_services(backend: str = "sim") -> tuple[str, ...]:
    """The services `tether up` starts to drive the robot through `backend` (a ROBOT_BACKENDS key)."""
    return (*ROBOT_BACKENDS[backend], *(s for s in SERVICES if s != "sim"))


# Not 7447: that is where rmw_zenoh's router listens on a ROS 2 robot (docs/ros2.md).
DEFAULT_BASE_PORT = 7460
DEFAULT_ROBOT = "robot1"
# Bigger queries are refused before decoding; a service may raise its own limit.
MAX_REQUEST_BYTES = 1024 * 1024
TRACE_PAYLOAD_LIMIT = 64 * 1024
# A process's queries are answered on kept worker threads (services/querypool.py), not a thread each.
# Most handlers answer within a few ms, some within seconds (a preempted goal's end, a camera frame):
# QUERY_WORKERS of them at once, QUERY_BACKLOG more queued; past that a query is answered "busy".
QUERY_WORKERS = 16
QUERY_BACKLOG = 64
# Handlers served with `waits` may block as long as a goal runs (get_result): a pool of their own, so
# they never take the workers of quick queries; one arriving with all of these taken is answered "busy".
WAITING_WORKERS = 64
# How long a thread holds the GIL while another waits for it (CPython's default: 5 ms), set by
# `tether run` for every service. A query's thread waiting behind the sim's physics loop or safety's
# heartbeat waited up to the whole 5 ms: most of a served query's p99. A bare queryable behind a
# 4 ms Python loop, queried from another process: p99 10-11 ms at 5 ms, 5 ms at 0.5 ms, p50 alike.
# The cost is a switch (a few us) at most every 0.5 ms, and only while two threads want the GIL.
SWITCH_INTERVAL = 0.0005
# Opening a Zenoh session on the loopback stack. Zenoh's open waits up to `scouting/delay` (500 ms) for
# every configured peer to have sent its declarations, and on loopback it always waited all of it: a
# port with no service behind it (the planner, the ROS 2 backends) never answers, and a peer that answers
# can be missed (zenoh 1.10 counts its declarations before it has noted who it linked to). Every service
# start, every `tether` command and every test session paid that half second. So a Node opens at once,
# waits (at most LINK_TIMEOUT) for a link to each service port that is listening, a client then (at
# most HEARD_TIMEOUT) for those services to answer a question (open_session says why), and for
# DISCOVERY seconds after that a query or a one-off publication first waits for Zenoh to know a
# queryable or subscriber for its key (Zenoh's matching status).
LINK_TIMEOUT = 2.0
HEARD_TIMEOUT = 2.0
DISCOVERY = 1.0
# zenoh-python (PyO3) refuses a call on an entity another thread is in a call on: an undeclare during
# a put raises "Already borrowed", a put during an undeclare "Already mutably borrowed" (RuntimeError).
CLOSE_RACE = "borrowed"


def closing_error(exc: Exception) -> bool:
    """Whether `exc` is what zenoh raises about a node being closed: its error for an entity undeclared or a
    session closed (ZError), or a call that met another thread's (CLOSE_RACE)."""
    return isinstance(exc, zenoh.ZError) or (isinstance(exc, RuntimeError) and CLOSE_RACE in str(exc))


@dataclass(frozen=True)
class NodeSettings:
    """Where a process finds the others: the robot's key prefix and the Zenoh configuration."""

    robot: str = DEFAULT_ROBOT
    base_port: int = DEFAULT_BASE_PORT
    host: str = "127.0.0.1"
    zenoh_config: Path | None = None

    def __post_init__(self) -> None:
        if not self.robot.replace("_", "").replace("-", "").isalnum():
            raise ValueError(f"robot name {self.robot!r} must be letters, digits, '-' or '_'")
        if not 1024 <= self.base_port <= 65535 - len(ALL_SERVICES):
            raise ValueError(f"base port {self.base_port} must be between 1024 and {65535 - len(ALL_SERVICES)}")
        if self.zenoh_config is not None and not self.zenoh_config.is_file():
            raise ValueError(f"zenoh config {self.zenoh_config} does not exist")

    @classmethod
    def from_env(cls, **overrides: Any) -> NodeSettings:
        """Settings from TETHER_ROBOT, TETHER_BASE_PORT and TETHER_ZENOH_CONFIG, then overrides."""
        values: dict[str, Any] = {}
        if robot := os.environ.get("TETHER_ROBOT"):
            values["robot"] = robot
        if port := os.environ.get("TETHER_BASE_PORT"):
            try:
                values["base_port"] = int(port)
            except ValueError:
                raise ValueError(f"TETHER_BASE_PORT={port!r} is not a port number") from None
        if conf := os.environ.get("TETHER_ZENOH_CONFIG"):
            values["zenoh_config"] = Path(conf)
        values.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**values)

    def endpoint(self, service: str) -> str:
        return f"tcp/{self.host}:{self.base_port + ALL_SERVICES.index(service)}"

    def zenoh(self, service: str | None) -> zenoh.Config:
        """A config file when one is given; else a loopback peer that nothing outside can reach."""
        if self.zenoh_config is not None:
            try:
                return zenoh_config_file(self.zenoh_config)
            except zenoh.ZError as exc:  # a service's config error, one line (a traceback before)
                raise ConfigError(f"Zenoh config file {self.zenoh_config} cannot be used: {exc}") from None
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("scouting/multicast/enabled", "false")
        listen = [self.endpoint(service)] if service in ALL_SERVICES else []
        connect = [self.endpoint(s) for s in ALL_SERVICES if s != service]
        conf.insert_json5("listen/endpoints", msgspec.json.encode(listen).decode())
        conf.insert_json5("connect/endpoints", msgspec.json.encode(connect).decode())
        # A peer not up yet (still starting, or not run at all, as the planner often is) is tried
        # again after 0.2 s, then at most every second; Zenoh's default backoff (1, 2, 4 s) left a
        # client started with the services blind to them for up to 7 s. Refused connects on
        # loopback cost nothing.
        retry = {"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}
        conf.insert_json5("connect/retry", msgspec.json.encode(retry).decode())
        # By default Zenoh copies every message over 3 KB into a 16 MB shared-memory pool of the sender's,
        # which each receiver maps as well: about 25 MB more resident per service after the demo
        # (bench.memory), to spare copies of messages that cross loopback TCP in microseconds anyway.
        conf.insert_json5("transport/shared_memory/transport_optimization/enabled", "false")
        return conf


def open_session(settings: NodeSettings, service: str | None) -> tuple[zenoh.Session, float]:
    """A session for `service` (None, or a name not in ALL_SERVICES: a client such as the CLI) and until
    when it is still discovering its peers (see DISCOVERY). A config file's session opens as Zenoh opens
    it, and so does one on a host whose listening ports cannot be read."""
    conf = settings.zenoh(service)
    ports = None if settings.zenoh_config is not None else listening_ports()
    if ports is None:
        return _open(conf), 0.0
    conf.insert_json5("scouting/delay", "0")
    listening = {s for i, s in enumerate(ALL_SERVICES) if s != service and settings.base_port + i in ports}
    session = _open(conf)
    endpoints = {settings.endpoint(s) for s in listening}
    linked: set[str] = set()
    changed = threading.Condition()

    def on_link(event: zenoh.LinkEvent) -> None:
        with changed:
            linked.add(str(event.link.dst))
            changed.notify_all()

    links = session.info.declare_link_events_listener(on_link, history=True)
    try:
        with changed:
            if not changed.wait_for(lambda: endpoints <= linked, timeout=LINK_TIMEOUT):
                log.debug("no link within %g s to %s", LINK_TIMEOUT, ", ".join(sorted(endpoints - linked)))
    finally:
        links.undeclare()
    if service not in ALL_SERVICES and endpoints & linked:
        # A client asks at once (who is alive, a call). A liveliness query ends once every linked peer
        # has answered it, and a peer answers in the order it was asked, a link's first question being
        # for all its declarations: at its end those are in, and later questions are answered from them.
        started = time.monotonic()
        for _ in session.liveliness().get(keys.alive_key(settings.robot, "*"), timeout=HEARD_TIMEOUT):
            pass
        if time.monotonic() - started >= HEARD_TIMEOUT:
            log.debug("not every service linked to answered within %g s", HEARD_TIMEOUT)
    return session, time.monotonic() + DISCOVERY


# After this long opening a session, a service says it is still waiting (for its router, most likely).
OPEN_NOTICE = 2.0


def _open(conf: zenoh.Config) -> zenoh.Session:
    """zenoh.open, which a client config waits in for its router for as long as it is down. In a
    service (stop_event was made) it waits on a thread of its own, so a stop meanwhile ends the
    service at once (SystemExit 0): blocked in zenoh.open, the main thread never ran the SIGTERM
    handler, and systemd or `tether up` had to kill it."""
    stopping = _stopping
    if stopping is None:
        return zenoh.open(conf)
    opened: list[zenoh.Session | BaseException] = []
    done = threading.Event()

    def open_it() -> None:
        try:
            opened.append(zenoh.open(conf))
        except BaseException as exc:  # handed to the main thread, which raises it
            opened.append(exc)
        finally:
            done.set()

    threading.Thread(target=open_it, name="zenoh-open", daemon=True).start()
    said_at = time.monotonic() + OPEN_NOTICE
    while not done.wait(SIGNAL_POLL):  # woken to run a signal's handler
        if stopping.is_set():
            log.info("stopped while its Zenoh session was opening (its router not up?)")
            raise SystemExit(0)
        if time.monotonic() > said_at:
            said_at = math.inf
            log.warning("no Zenoh session after %g s: waiting for %s", OPEN_NOTICE, conf.get_json("connect/endpoints"))
    if isinstance(opened[0], BaseException):
        raise opened[0]
    return opened[0]


# The file paths a Zenoh config may hold: TLS keys, certificates and CA, and the router's password list.
CONFIG_FILE_PATHS = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/connect_private_key",
    "transport/link/tls/connect_certificate",
    "transport/auth/usrpwd/dictionary_file",
)


def zenoh_config_file(path: Path) -> zenoh.Config:
    """A Zenoh config file, its relative file paths taken from the file's own directory (Zenoh would take
    them from the working directory), so a deployment's files can be moved together."""
    conf = zenoh.Config.from_file(str(path))
    for item in CONFIG_FILE_PATHS:
        value = json.loads(conf.get_json(item))
        if isinstance(value, str) and value and not Path(value).is_absolute():
            conf.insert_json5(item, json.dumps(str(path.resolve().parent / value)))
    return conf


# msgspec (0.22) is not safe building a type's description (a decoder, a first typed decode or
# convert) on two threads at once; see decoder. Whatever does so off its main thread holds this, one
# lock for the whole process: two types may share the struct types they hold.
BUILDING_TYPES = threading.RLock()
_decoders: dict[Any, msgspec.json.Decoder[Any]] = {}


_prepared: set[type] = set()


def prepare_types() -> None:
    """Build the description of every msgspec Struct type imported so far, here, one at a time: the
    first use of a struct type (a decode, a convert, a YAML file read into one) on two threads at once
    crashed the process (see decoder), and a service's threads each meet many types first. Called as a
    Node opens and as it declares what it serves and hears, before any callback can run; cheap when
    nothing new was imported (a 205-type stack takes 12 ms once)."""
    with BUILDING_TYPES:
        stack: list[type] = [msgspec.Struct]
        while stack:
            subclasses: list[type] = stack.pop().__subclasses__()
            for struct in subclasses:
                stack.append(struct)
                if struct not in _prepared:
                    _prepared.add(struct)
                    # One msgspec cannot decode never is. A NameError: a type whose module's import was cut
                    # short (a Ctrl-C in a lazy import) names what that module never got to define.
                    with contextlib.suppress(TypeError, ValueError, NameError):
                        msgspec.json.Decoder(struct)


def decoder(type_: Any) -> msgspec.json.Decoder[Any]:
    """One decoder per type, built once, and one at a time: msgspec (0.22) caches a struct type's
    description on the type before it has filled it in, so a decoder built on another thread
    meanwhile took the half-made one, and its first decode crashed the process (SIGSEGV: a planner
    asked three plan/ask requests at once, each asking safety for incidents). A decoder already
    built is taken without the lock: a call's reply decoder is looked up on every call."""
    found = _decoders.get(type_)
    if found is None:
        with BUILDING_TYPES:
            found = _decoders.get(type_)
            if found is None:
                found = _decoders[type_] = msgspec.json.Decoder(type_)
    return found


_encoder = msgspec.json.Encoder()


def encode(message: Any) -> bytes:
    return _encoder.encode(message)


# Checks a message before it is decoded: None to take it, else why it is refused (the check reports it).
Verify = Callable[[str, bytes, bytes | None], Refusal | None]


def _attachment(item: zenoh.Sample | zenoh.Query) -> bytes | None:
    attachment = item.attachment
    return None if attachment is None else attachment.to_bytes()


class Publisher(Generic[T]):
    def __init__(self, publisher: zenoh.Publisher, node: Node) -> None:
        self._publisher = publisher
        self._node = node
        self._key = str(publisher.key_expr)

    def put(self, message: T) -> None:
        self._node._send(self._key, encode(message), self._publisher.put)


class Subscription:
    """A subscriber that can be dropped before its node closes."""

    def __init__(self, node: Node, subscriber: zenoh.Subscriber[Any]) -> None:
        self._node = node
        self._subscriber = subscriber

    def undeclare(self) -> None:
        self._node._forget(self._subscriber)


class Node:
    """One process's Zenoh session, bound to one robot's keys, under one service name."""

    def __init__(self, service: str, settings: NodeSettings) -> None:
        self.service = service
        self.settings = settings
        self.robot = settings.robot
        prepare_types()  # before Zenoh's threads can call anything of this node
        self.session, self._discovering_until = open_session(settings, service)
        self._matched: set[str] = set()  # keys found served or subscribed while discovering
        self._declared: list[Any] = []
        self.closed = False  # set first thing in close: what is published after it is dropped
        self._trace_publishers: dict[str, zenoh.Publisher] = {}
        self._lock = threading.Lock()
        # Threads start with the first query that needs one (services/querypool.py).
        self.queries = QueryPool(f"q:{service}", QUERY_WORKERS, QUERY_BACKLOG)
        self.waiting_queries = QueryPool(f"w:{service}", WAITING_WORKERS)
        # Safety's: signs what it sends to the robot (services/robotlink.py); None: nothing is signed.
        self.signer: Signer | None = None
        self.undecodable = RepeatLog("undecodable messages dropped")
        self.overloaded = RepeatLog("queries answered busy")
        # Told (key, the log line, how many it tells of) with each line about undecodable messages:
        # a service may publish it as an event too (safety does, on safety/events).
        self.on_undecodable: Callable[[str, str, int], None] | None = None

    # Topics

    def publisher(self, topic: Topic[T]) -> Publisher[T]:
        pub = self.session.declare_publisher(topic.key(self.robot), **_qos(topic))
        self._declared.append(pub)
        return Publisher(pub, self)

    def publish(self, topic: Topic[T], message: T) -> None:
        key = topic.key(self.robot)
        self._until_matched(key, lambda: self.session.declare_publisher(key), DISCOVERY)
        qos = _qos(topic)

        def put(payload: bytes, **signature: Any) -> None:
            self.session.put(key, payload, **qos, **signature)

        self._send(key, encode(message), put)

    def _send(self, key: str, payload: bytes, put: Callable[..., object]) -> None:
        """`put(payload)` for `key`, with safety's MAC as its attachment when this node signs and the
        key needs one (services/robotlink.py): signed and sent in one step, so the counters go out in order."""
        signer = self.signer
        try:
            if signer is None or not signed(key):
                put(payload)
                return
            with signer.lock:
                put(payload, attachment=signer.sign(key, payload))
        except (zenoh.ZError, RuntimeError) as exc:
            if not (self.closed and closing_error(exc)):
                raise
            # A thread of the service still at work while it shuts down: nothing can be sent any more.
            log.debug("%s not published: the node is closed", key)

    def _undecodable(self, key: object, what: str, exc: Exception) -> None:
        """A flood of bad bytes is one line, then a count every few seconds (services/repeats.py)."""
        if (line := self.undecodable.note(str(key), f"{what}: {exc}")) is not None:
            log.warning("%s", line)
            if (report := self.on_undecodable) is not None:
                try:
                    report(str(key), line, self.undecodable.covered(str(key)))
                except Exception:
                    log.exception("reporting undecodable messages on %s failed", key)

    def subscribe(
        self, topic: Topic[T], callback: Callable[[T], None], *, verify: Verify | None = None
    ) -> Subscription:
        """Subscribe with a typed callback; a sample that does not decode is logged and dropped, and
        one `verify` refuses is dropped before decoding."""
        prepare_types()  # what was imported since the node opened (a service's lazy imports)
        dec = decoder(cast(Any, topic.type))
        key = topic.key(self.robot)

        def on_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload.to_bytes()
            if verify is not None and verify(str(sample.key_expr), payload, _attachment(sample)) is not None:
                return
            try:
                message = dec.decode(payload)
            except DECODE_ERRORS as exc:
                # Counted under the topic's key: a peer's puts on endless made-up wildcard expressions
                # ("tether/r1/robot/o$*dom") all reach this subscriber, each a line and a report of its own.
                sent = str(sample.key_expr)
                self._undecodable(key, "sample" if sent == key else f"sample sent to {sent[:200]!r}", exc)
                return
            try:
                callback(message)
            except Exception:
                log.exception("subscriber callback for %s failed", key)

        subscriber = self.session.declare_subscriber(key, on_sample)
        self._declared.append(subscriber)
        return Subscription(self, subscriber)

    def subscribe_raw(self, key_expr: str, callback: Callable[..., None], *, attachments: bool = False) -> None:
        """`callback(key, payload)`, or with `attachments` `callback(key, payload, attachment or None)`."""

        def on_sample(sample: zenoh.Sample) -> None:
            if attachments:
                callback(str(sample.key_expr), sample.payload.to_bytes(), _attachment(sample))
            else:
                callback(str(sample.key_expr), sample.payload.to_bytes())

        self._declared.append(self.session.declare_subscriber(key_expr, on_sample))

    # Services

    def serve(
        self,
        service: Service[Q, A],
        handler: Callable[[Q], A],
        *,
        max_request_bytes: int = MAX_REQUEST_BYTES,
        inline: bool | Callable[[Q], bool] = False,
        waits: bool = False,
        after: Callable[[Q, A], None] | None = None,
        verify: Verify | None = None,
    ) -> None:
        """Answer queries on `service`. Always replies: with the handler's value or a ServiceError.

        Handlers run on this node's kept worker threads (`queries`), so one may block for a while (a
        forwarded query, a camera frame) without holding up Zenoh's callback thread. One that waits
        as long as a goal runs (get_result) is served with `waits`, on a pool of its own
        (`waiting_queries`), so it never takes a quick query's worker. A query that finds its pool
        full is answered at once with an `unavailable` error saying how full. `inline` handlers are
        quick and never block (parsing): they run on Zenoh's callback thread, with no hand-over.
        `inline` may also be a test of the decoded request (a goal that will not wait for another
        to end): then requests are decoded on the callback thread, those it passes answered there,
        the others handed to a worker with their decoded request.

        The request is decoded once, the reply encoded once. `after(request, reply)` runs once the
        reply has gone (or failed to go): work the asker need not wait for, such as starting an
        accepted goal or writing the log line. Then each query and its reply is published on
        `_trace/**`, the request as it came (re-encoded only to redact). A query `verify` refuses gets
        an unauthorized error and never reaches the handler; it is checked on Zenoh's callback
        thread, in the order queries arrive.
        """
        prepare_types()
        dec = decoder(cast(Any, service.request))
        key = service.key(self.robot)
        # Parsed once: a reply's key given as a string is parsed again for every reply.
        reply_key = zenoh.KeyExpr(key)
        pool = self.waiting_queries if waits else self.queries

        def read(raw: bytes) -> tuple[float, bytes, Any, ServiceError | None]:
            """(when it was read, its bytes, the request decoded or None, the error that refuses it or None)."""
            started = time.time()
            if len(raw) > max_request_bytes:
                message = f"request is {len(raw)} bytes; {service.path} accepts at most {max_request_bytes}"
                return started, raw, None, ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)
            try:
                return started, raw, dec.decode(raw), None
            except DECODE_ERRORS as exc:
                self._undecodable(key, "request", exc)
                message = f"invalid request for {service.path}: {exc}"
                return started, raw, None, ServiceError(kind=ErrorKind.INVALID_REQUEST, message=message)

        def respond(query: zenoh.Query, started: float, raw: bytes, request: Any, error: ServiceError | None) -> None:
            """Reply to a read query (with `error` if it is refused), then what follows, then its trace."""
            decoded, answered = error is None, False
            value: Any = None
            reply: bytes | None = None
            try:
                if error is None:
                    try:
                        value = handler(request)
                        reply = encode(value)
                        answered = True  # a value that does not encode is answered with an error, and nothing follows
                    except CallError as exc:
                        error = exc.error
                    except Exception as exc:
                        log.exception("handler for %s failed", key)
                        error = ServiceError(kind=ErrorKind.INTERNAL, message=f"{service.path} failed: {exc}")
                if error is not None:
                    query.reply_err(encode(error))
                else:
                    assert reply is not None
                    query.reply(reply_key, reply)
            finally:
                query.drop()
                finished = time.time()
                if answered and after is not None:
                    try:
                        after(request, value)
                    except Exception:
                        log.exception("what follows the reply on %s failed", key)
            kept: bytes | None = None
            if decoded:
                kept = raw
                if service.redact:
                    kept = encode(msgspec.structs.replace(request, **dict.fromkeys(service.redact, "(redacted)")))
            self._trace(service.path, started, finished, kept, raw, reply, error)

        def answer(query: zenoh.Query, raw: bytes) -> None:
            respond(query, *read(raw))

        def turn_away(query: zenoh.Query, raw: bytes, error: ServiceError) -> None:
            """Answer with `error` without handling the query; traced like any query answered (a
            recording shows who tried what: tether inspect flags it)."""
            started = time.time()
            try:
                query.reply_err(encode(error))
            finally:
                query.drop()
            self._trace(service.path, started, time.time(), None, raw, None, error)

        def refused(query: zenoh.Query, raw: bytes) -> bool:
            if verify is None:
                return False
            refusal = verify(str(query.key_expr), raw, _attachment(query))
            if refusal is None:
                return False
            turn_away(
                query, raw, ServiceError(kind=ErrorKind.UNAUTHORIZED, message=f"{service.path} refused: {refusal}")
            )
            return True

        def busy(query: zenoh.Query, raw: bytes) -> None:
            """Answer at once that there is no worker for it; the query is not handled."""
            load = pool.load()
            message = f"{self.service} is too busy to answer {service.path} ({load}); try again"
            turn_away(query, raw, ServiceError(kind=ErrorKind.UNAVAILABLE, message=message))
            if (line := self.overloaded.note(key, load)) is not None:
                log.warning("%s", line)

        def here(request: Any) -> bool:
            """Whether a decoded request is answered on the callback thread (`inline` as a test)."""
            assert callable(inline)
            try:
                return inline(request)
            except Exception:
                log.exception("deciding where to answer %s failed; answered on a worker", key)
                return False

        def on_query(query: zenoh.Query) -> None:
            # The payload is copied out once, here, for the signature check, decoding and the trace.
            raw = query.payload.to_bytes() if query.payload is not None else b""
            if refused(query, raw):
                return
            if inline is True:
                answer(query, raw)
            elif inline is False:
                if not pool.submit(functools.partial(answer, query, raw)):
                    busy(query, raw)
            else:
                started, raw, request, error = read(raw)
                if error is not None or here(request):
                    respond(query, started, raw, request, error)
                elif not pool.submit(functools.partial(respond, query, started, raw, request, None)):
                    busy(query, raw)

        self._declared.append(self.session.declare_queryable(key, on_query))

    def call(self, service: Service[Q, A], request: Q, *, timeout: float = 5.0) -> A:
        """Ask `service` and return its reply; raise CallError on an error reply or none at all."""
        key, payload = service.key(self.robot), encode(request)
        self._until_matched(key, lambda: self.session.declare_querier(key), timeout)
        asked = time.monotonic()  # after any wait for a queryable: `waited` below is the query's own
        signer = self.signer
        try:
            if signer is None or not signed(key):
                replies = self.session.get(key, payload=payload, timeout=timeout)
            else:
                with signer.lock:  # the get only sends here; its replies are read below, outside the lock
                    attachment = signer.sign(key, payload)
                    replies = self.session.get(key, payload=payload, timeout=timeout, attachment=attachment)
        except (zenoh.ZError, RuntimeError) as exc:
            if not (self.closed and closing_error(exc)):
                raise
            # A thread of the service still at work as it shuts down: what its callers handle.
            message = f"no reply from {service.path}: this {self.service} session closed"
            raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=message)) from None
        for reply in replies:
            if reply.ok is not None:
                try:
                    return decoder(service.reply).decode(reply.ok.payload.to_bytes())  # type: ignore[no-any-return]
                except DECODE_ERRORS as exc:
                    message = f"undecodable reply from {service.path}: {exc}"
                    raise CallError(ServiceError(kind=ErrorKind.INTERNAL, message=message)) from None
            payload = reply.err.payload.to_bytes() if reply.err is not None else b""
            try:
                error = decoder(ServiceError).decode(payload)
            except DECODE_ERRORS:
                error = ServiceError(kind=ErrorKind.INTERNAL, message=payload[:500].decode(errors="replace"))
            raise CallError(error)
        waited = time.monotonic() - asked
        if self.closed:  # the session was closed under the query, not that nothing serves the key
            message = f"no reply from {service.path}: this {self.service} session closed after {waited:.2f} s"
        elif waited < timeout * 0.9:  # Zenoh ended the query early: nothing serving the key answered it
            # At once: nothing serves it here ("within 0.00 s" said nothing).
            within = f" within {waited:.2f} s" if waited >= 0.01 else ""
            message = f"no reply from {service.path}: nothing answered it{within} (is it running?)"
        else:
            message = f"no reply from {service.path} within {timeout:g} s"
        raise CallError(ServiceError(kind=ErrorKind.UNAVAILABLE, message=message))

    def _trace(
        self,
        path: str,
        started: float,
        finished: float,
        request: bytes | None,
        raw: bytes,
        reply: bytes | None,
        error: ServiceError | None,
    ) -> None:
        """Publish a query served on `path`: `request` is its JSON as kept (None: not decoded, then only
        the size of `raw` is told), `reply` the reply's (kept up to TRACE_PAYLOAD_LIMIT)."""
        record = TraceRecord(
            stamp=started,
            service=self.service,
            key=path,
            duration=finished - started,
            query=msgspec.Raw(request if request is not None else b"null"),
            reply=msgspec.Raw(reply if reply is not None and len(reply) <= TRACE_PAYLOAD_LIMIT else b"null"),
            error=error.message if error else "",
        )
        if request is None and raw:
            record = msgspec.structs.replace(record, error=f"{record.error} (request of {len(raw)} bytes not kept)")
        key = keys.trace_key(self.robot, self.service, path)
        try:
            with self._lock:
                pub = self._trace_publishers.get(key)
                if pub is None:
                    # A handler still running as the node closed declares on a closed session.
                    pub = self._trace_publishers[key] = self.session.declare_publisher(key)
            pub.put(encode(record))
        except zenoh.ZError:
            log.debug("trace for %s not published: session closing", path)

    def _until_matched(self, key: str, declare: Callable[[], zenoh.Publisher | zenoh.Querier], longest: float) -> None:
        """In a session opened moments ago, wait (until DISCOVERY has passed, `longest` at most) for
        Zenoh to know a subscriber or queryable for `key`, which `declare` declares; at once when it
        does, and not again for a key it once did."""
        left = min(self._discovering_until - time.monotonic(), longest)
        if left <= 0 or key in self._matched:
            return
        try:
            entity = declare()
        except (zenoh.ZError, RuntimeError) as exc:
            if not (self.closed and closing_error(exc)):
                raise
            return  # the node closed: the put or get that follows says so
        try:
            matched = threading.Event()
            listener = entity.declare_matching_listener(lambda status: matched.set() if status.matching else None)
            # zenoh's stub says a bool; it is a MatchingStatus, as the listener is given
            if cast(zenoh.MatchingStatus, entity.matching_status).matching or matched.wait(left):
                self._matched.add(key)
            listener.undeclare()
        finally:
            entity.undeclare()

    # Liveliness

    def declare_alive(self) -> None:
        if os.environ.get(BENCH_ECHO_ENV) == "1":
            self.declare_bench_echo()
        if relay_to := os.environ.get(BENCH_RELAY_ENV):
            self.declare_bench_relay(relay_to)
        self.declare_process_status()
        self._declared.append(self.session.liveliness().declare_token(keys.alive_key(self.robot, self.service)))

    def declare_process_status(self) -> None:
        """Answer `keys.process_key` with this process's figures (services.procstat), for `tether status`.

        Before the liveliness token, so whoever sees the service alive can ask at once. Not traced:
        it is about the process, not the robot, and `tether status` would fill recordings with it.
        """
        key = keys.process_key(self.robot, self.service)

        def answer(query: zenoh.Query) -> None:
            try:
                query.reply(key, encode(process_status(self.service)))
            finally:
                query.drop()

        self._declared.append(self.session.declare_queryable(key, answer))

    def process_statuses(self, timeout: float = 1.0) -> dict[str, ProcessStatus]:
        """Each service's ProcessStatus, from those that answer within `timeout`, by service name."""
        replies = self.session.get(
            keys.process_key(self.robot, "*"),
            target=zenoh.QueryTarget.ALL,
            consolidation=zenoh.ConsolidationMode.NONE,
            timeout=timeout,
        )
        found: dict[str, ProcessStatus] = {}
        for reply in replies:
            if reply.ok is None:
                continue
            # The name is the key's (the access rules let each identity answer only on its own);
            # a reply whose body names another service is someone claiming to be it, and dropped.
            key = str(reply.ok.key_expr)
            try:
                status = decoder(ProcessStatus).decode(reply.ok.payload.to_bytes())
            except DECODE_ERRORS as exc:
                self._undecodable(key, "process status", exc)
                continue
            if key != keys.process_key(self.robot, status.service):
                log.warning("dropped a process status for %r answered on %s", status.service, key)
                continue
            found[status.service] = status
        return found

    def declare_bench_echo(self) -> None:
        """A bare Zenoh echo on this session: the baseline a benchmark compares this service's queries with.

        Declared by every service started with TETHER_BENCH_ECHO=1 (benchmarks only; off by default).
        """
        key = keys.bench_echo_key(self.robot, self.service)

        def echo(query: zenoh.Query) -> None:
            try:
                query.reply(key, query.payload.to_bytes() if query.payload is not None else b"")
            finally:
                query.drop()

        self._declared.append(self.session.declare_queryable(key, echo))

    def declare_bench_relay(self, target: str) -> None:
        """Bare Zenoh relays through this session: the baseline for commands passing through this service.

        A query on `bench_relay_key` is forwarded as it is, with a plain get, to `target`'s bench echo,
        and the first reply's bytes go back; samples on `bench_stream_in_key` are put again on
        `bench_stream_out_key`. No decoding and no checks. Declared with TETHER_BENCH_RELAY=<target>.
        """
        key, echo = keys.bench_relay_key(self.robot), keys.bench_echo_key(self.robot, target)

        def relay(query: zenoh.Query) -> None:
            try:
                payload = query.payload.to_bytes() if query.payload is not None else b""
                for reply in self.session.get(echo, payload=payload, timeout=BENCH_RELAY_TIMEOUT):
                    if reply.ok is not None:
                        query.reply(key, reply.ok.payload.to_bytes())
                    else:
                        query.reply_err(reply.err.payload.to_bytes() if reply.err is not None else b"")
                    return
                query.reply_err(f"no reply from {echo}".encode())
            finally:
                query.drop()

        out = self.session.declare_publisher(keys.bench_stream_out_key(self.robot))
        self._declared.append(out)
        self._declared.append(self.session.declare_queryable(key, relay))
        self._declared.append(
            self.session.declare_subscriber(
                keys.bench_stream_in_key(self.robot), lambda sample: out.put(sample.payload.to_bytes())
            )
        )

    def alive_services(self, timeout: float = 1.0) -> set[str]:
        replies = self.session.liveliness().get(keys.alive_key(self.robot, "*"), timeout=timeout)
        return {str(r.ok.key_expr).rsplit("/", 1)[-1] for r in replies if r.ok is not None}

    def is_alive(self, service: str, timeout: float) -> bool:
        """Whether `service` holds its liveliness token, heard within `timeout`. A liveliness get
        (alive_services) answers from the tokens heard when it is asked: from a session opened a moment
        before, on a loaded machine, that missed a running resolver ("no resolver reachable")."""
        return not self.wait_alive([service], timeout)

    def wait_alive(self, services: Iterable[str], timeout: float) -> set[str]:
        """Wait until all `services` hold liveliness tokens; return those still missing at the deadline."""
        wanted = set(services)
        seen: set[str] = set()
        changed = threading.Condition()

        def on_token(sample: zenoh.Sample) -> None:
            name = str(sample.key_expr).rsplit("/", 1)[-1]
            with changed:
                if sample.kind == zenoh.SampleKind.PUT:
                    seen.add(name)
                else:
                    seen.discard(name)
                changed.notify_all()

        sub = self.session.liveliness().declare_subscriber(keys.alive_key(self.robot, "*"), on_token, history=True)
        try:
            with changed:
                changed.wait_for(lambda: wanted <= seen, timeout=timeout)
                return wanted - seen
        finally:
            sub.undeclare()

    def watch_alive(self, service: str, changed: Callable[[bool], None]) -> None:
        """Call `changed(True)` when `service` comes alive (its liveliness token; also one held when
        this is called) and `changed(False)` when it goes away: it closed its session, or its link
        was lost for longer than Zenoh's lease. On Zenoh's callback thread."""

        def on_token(sample: zenoh.Sample) -> None:
            try:
                changed(sample.kind == zenoh.SampleKind.PUT)
            except Exception:
                log.exception("handling %s's liveliness failed", service)

        key = keys.alive_key(self.robot, service)
        self._declared.append(self.session.liveliness().declare_subscriber(key, on_token, history=True))

    def _forget(self, item: Any) -> None:
        if item in self._declared:
            self._declared.remove(item)
            with contextlib.suppress(zenoh.ZError):
                item.undeclare()

    def close(self) -> None:
        self.closed = True
        for item in reversed(self._declared):
            try:
                item.undeclare()
            except (zenoh.ZError, RuntimeError) as exc:
                if not closing_error(exc):
                    raise
                # Undeclared already, or another thread is in a call on it (a publisher's put, say):
                # the session's close below takes it down with the rest.
        self._declared.clear()
        self.session.close()

    def __enter__(self) -> Node:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# Sent by the supervisor to a service that did not stop in time, just before SIGKILL: every thread's
# stack goes to stderr (the service's log), which says where it was stuck.
DUMP_STACKS = signal.SIGUSR1


# How often a main thread waiting for its stop event wakes (see StopEvent).
SIGNAL_POLL = 0.2


class StopEvent(threading.Event):
    """A threading.Event whose waits wake every SIGNAL_POLL seconds.

    The kernel may deliver SIGTERM to any thread, Zenoh's own among them. Python then only flags it,
    and runs the handler when the main thread next runs: a main thread blocked in an untimed
    Event.wait() never does, and the service would outlive its stop until the supervisor kills it.
    """

    def wait(self, timeout: float | None = None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            left = SIGNAL_POLL if deadline is None else min(SIGNAL_POLL, deadline - time.monotonic())
            if super().wait(max(0.0, left)):
                return True
            if deadline is not None and time.monotonic() >= deadline:
                return False


# The stop event of this process when it is a service (stop_event): what a session opening looks at.
_stopping: StopEvent | None = None


def stop_event(*, hangup: bool = False) -> threading.Event:
    """An event set by SIGINT or SIGTERM, for a service's main loop to wait on; with `hangup`, by
    SIGHUP too (a command whose terminal closes ends as on Ctrl-C)."""
    global _stopping
    stop = _stopping = StopEvent()

    def handle(signum: int, _frame: object) -> None:
        log.info("received %s, shutting down", signal.Signals(signum).name)
        stop.set()

    for signum in (signal.SIGINT, signal.SIGTERM, *((signal.SIGHUP,) if hangup else ())):
        signal.signal(signum, handle)
    faulthandler.register(DUMP_STACKS, all_threads=True)
    return stop


# A service's config file is a few KB; the limit only keeps a wrong or hostile file from being read whole.
MAX_CONFIG_BYTES = 1024 * 1024


class ConfigError(Exception):
    """A config file is unreadable or a value in it is out of bounds; the message names both."""


def load_config(cls: type[C], path: Path | None, section: str) -> C:
    """A service's frozen config from the `[section]` table of a TOML file; defaults without a file."""
    if path is None:
        return msgspec.convert({}, cls)
    # A FIFO given as the config hung start-up, and a device (/dev/zero) would be read without end.
    _, raw = read_bounded(path, MAX_CONFIG_BYTES, "config", ConfigError)
    try:
        data = tomllib.loads(raw.decode())
    except UnicodeDecodeError as exc:
        raise ConfigError(f"config file {path} is not UTF-8 text (byte {exc.start} is not)") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path} is not valid TOML: {exc}") from None
    except RecursionError:
        raise ConfigError(f"config file {path} nests arrays or tables too deeply") from None
    except ValueError:  # past Python's limit on the digits of an integer it parses
        raise ConfigError(f"config file {path} holds a number of too many digits") from None
    # Every service reads its own table of one shared file: a misspelt one ([saftey]) was read by none,
    # and its service ran on its defaults without a word.
    if unknown := [name for name in data if name not in ALL_SERVICES]:
        shown = ", ".join(f"[{name}]" for name in unknown[:5]).translate(_LOG_CONTROLS)[:300]
        tables = ", ".join(f"[{name}]" for name in ALL_SERVICES)
        raise ConfigError(f"config file {path}: {shown} is no service's table (the tables are {tables})")
    try:
        return msgspec.convert(data.get(section, {}), cls)
    except msgspec.ValidationError as exc:
        # It quotes the file (an unknown field's name): shown on a terminal, its ESC sequences are escaped.
        raise ConfigError(f"config file {path} [{section}]: {str(exc).translate(_LOG_CONTROLS)}") from None


# Control characters (C0, DEL, C1) as text shows them escaped (`\\x1b`), for str.translate: what others
# wrote, before it reaches a terminal or a journal (and tether/output.py's printable).
CONTROLS = {code: f"\\x{code:02x}" for code in (*range(0x20), *range(0x7F, 0xA0))}
# Those a log line escapes (newlines and tabs stay: tracebacks).
_LOG_CONTROLS = {code: escaped for code, escaped in CONTROLS.items() if chr(code) not in "\n\t"}


def _qos(topic: Topic[Any]) -> dict[str, Any]:
    """How a topic's messages are sent: an urgent one (keys.Topic) at Zenoh's real-time priority,
    blocking rather than dropped when the link's queue is full, and sent at once, not batched."""
    if not topic.urgent:
        return {}
    return {"priority": zenoh.Priority.REAL_TIME, "congestion_control": zenoh.CongestionControl.BLOCK, "express": True}


class _EscapingFormatter(logging.Formatter):
    """Log lines quote what others wrote (an e-stop's reason, a plan's step, a robot's error): their
    ESC sequences are escaped, so none retitles or repaints the terminal or journal they are read in."""

    def format(self, record: logging.LogRecord) -> str:
        return super().format(record).translate(_LOG_CONTROLS)


def configure_logging(level: str = "INFO") -> None:
    """Log lines to stderr at TETHER_LOG_LEVEL, else `level`; a level logging does not know (a typo
    in a unit file) is said in one line, and `level` is used: it ended the service with a traceback."""
    handler = logging.StreamHandler()
    handler.setFormatter(_EscapingFormatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    asked = os.environ.get("TETHER_LOG_LEVEL", level)
    known = asked.upper() in logging.getLevelNamesMapping()
    logging.basicConfig(level=asked.upper() if known else level.upper(), handlers=[handler])
    if not known:
        log.warning("TETHER_LOG_LEVEL=%r is not a log level (DEBUG, INFO, WARNING, ERROR); logging at %s", asked, level)
