"""Hosts as network namespaces joined by veth pairs on link-local addresses, their processes, and clean-up.

The topology: an edge host holding a bridge (169.254.0.1, where the router listens, and 169.254.0.2,
the same router for the robot's link proxy), and any number of hosts, each a namespace with one veth
(`eth0`, 169.254.0.(10+i)/16) whose other end sits on the edge's bridge. Names carry a prefix and the
pid of the process that made them, so a sweep can remove what a killed run left behind without
touching a live run's.
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from tests.multihost.linkproxy import ProxyControl

PREFIX = "tmh"
ROUTER_IP = "169.254.0.1"
ROUTER_PORT = 7470
# A second address of the edge's bridge: the robot's link proxy reaches the router here, since on
# the robot host ROUTER_IP is the proxy's own (local) address.
ROUTER_ALT_IP = "169.254.0.2"
HOST_DEVICE = "eth0"
STOP_TIMEOUT = 10.0
READY_TIMEOUT = 10.0
_NAME = re.compile(rf"^{PREFIX}(\d+)x")
_counter = 0


class NetnsError(RuntimeError):
    """An `ip` or `tc` command failed; the message has the command and what it printed."""


def sh(*argv: str) -> str:
    done = subprocess.run(argv, capture_output=True, text=True, timeout=30)
    if done.returncode != 0:
        raise NetnsError(f"{' '.join(argv)}: exit {done.returncode}: {done.stderr.strip() or done.stdout.strip()}")
    return done.stdout


def unavailable() -> str | None:
    """Why namespaces cannot be made here (not root, no `ip`, `ip netns add` refused), or None."""
    if os.geteuid() != 0:
        return "network namespaces need root (ip netns add); not running as root"
    probe = f"{PREFIX}{os.getpid()}xprobe"
    try:
        sh("ip", "netns", "add", probe)
    except (NetnsError, FileNotFoundError) as exc:
        return f"cannot create a network namespace: {exc}"
    with contextlib.suppress(NetnsError):
        sh("ip", "netns", "del", probe)
    return None


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _kill_inside(netns: str) -> None:
    """SIGKILL every process still in `netns` (the services `tether up` started in their own sessions too)."""
    with contextlib.suppress(NetnsError):
        for pid in sh("ip", "netns", "pids", netns).split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)


def sweep_stale() -> list[str]:
    """Delete the namespaces (and with them their veths) of runs whose process is gone; return their names."""
    swept = []
    for line in sh("ip", "netns", "list").splitlines():
        name = line.split()[0] if line.split() else ""
        match = _NAME.match(name)
        if match and not _alive(int(match.group(1))):
            _kill_inside(name)
            with contextlib.suppress(NetnsError):
                sh("ip", "netns", "del", name)
            swept.append(name)
    return swept


@dataclass
class Host:
    role: str
    netns: str
    address: str  # on its eth0
    device: str = HOST_DEVICE
    narrowed: bool = False


@dataclass
class Proc:
    name: str
    host: str  # a role, or "root"
    popen: subprocess.Popen[bytes]
    log: Path
    out: IO[bytes] = field(repr=False)

    def tail(self, lines: int = 40) -> str:
        self.out.flush()
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-lines:])


class Topology:
    """An edge host and `roles` hosts joined to its bridge; processes started in them; torn down by close()."""

    def __init__(self, roles: Sequence[str], workdir: Path) -> None:
        global _counter
        _counter += 1
        self.tag = f"{PREFIX}{os.getpid()}x{_counter}"
        self.workdir = workdir
        self.logs = workdir / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)
        self.edge = Host("edge", f"{self.tag}edge", ROUTER_IP, device="br0")
        self.hosts = {role: Host(role, f"{self.tag}{role}", f"169.254.0.{10 + i}") for i, role in enumerate(roles)}
        self.procs: list[Proc] = []
        self.proxies: dict[str, ProxyControl] = {}
        self._made: list[str] = []
        try:
            self._build()
        except BaseException:
            self.close()
            raise

    def _build(self) -> None:
        edge = self.edge.netns
        self._add_netns(edge)
        sh("ip", "-n", edge, "link", "add", "br0", "type", "bridge")
        sh("ip", "-n", edge, "addr", "add", f"{ROUTER_IP}/16", "dev", "br0")
        sh("ip", "-n", edge, "addr", "add", f"{ROUTER_ALT_IP}/16", "dev", "br0")
        sh("ip", "-n", edge, "link", "set", "br0", "up")
        for host in self.hosts.values():
            self._add_netns(host.netns)
            peer = f"v{host.role}"[:15]
            sh(
                "ip",
                "link",
                "add",
                host.device,
                "netns",
                host.netns,
                "type",
                "veth",
                "peer",
                "name",
                peer,
                "netns",
                edge,
            )
            sh("ip", "-n", edge, "link", "set", peer, "master", "br0")
            sh("ip", "-n", edge, "link", "set", peer, "up")
            sh("ip", "-n", host.netns, "addr", "add", f"{host.address}/16", "dev", host.device)
            sh("ip", "-n", host.netns, "link", "set", host.device, "up")

    def _add_netns(self, name: str) -> None:
        sh("ip", "netns", "add", name)
        self._made.append(name)
        sh("ip", "-n", name, "link", "set", "lo", "up")

    def host(self, role: str) -> Host:
        return self.edge if role == "edge" else self.hosts[role]

    # Faults on a host's link

    def cut(self, role: str) -> float:
        """Take the host's link down (its veth, no carrier: packets vanish, nobody is told); time.time() of it."""
        host = self.hosts[role]
        at = time.time()
        sh("ip", "-n", host.netns, "link", "set", host.device, "down")
        return at

    def restore(self, role: str) -> float:
        host = self.hosts[role]
        sh("ip", "-n", host.netns, "link", "set", host.device, "up")
        return time.time()

    def narrow(self, role: str, rate: str = "256kbit", burst: str = "16kb", latency: str = "100ms") -> None:
        """A token bucket (tc tbf) on the host's outgoing side: a slow link that queues, then drops."""
        host = self.hosts[role]
        sh("tc", "-n", host.netns, "qdisc", "replace", "dev", host.device, "root", "tbf", "rate", rate, "burst", burst,
           "latency", latency)  # fmt: skip
        host.narrowed = True

    def widen(self, role: str) -> None:
        host = self.hosts[role]
        if host.narrowed:
            sh("tc", "-n", host.netns, "qdisc", "del", "dev", host.device, "root")
            host.narrowed = False

    # Processes

    def spawn(self, role: str, name: str, argv: Sequence[str], env: dict[str, str] | None = None) -> Proc:
        """Start `argv` in host `role` ("root": this namespace) in its own session, output to logs/<name>.log."""
        log = self.logs / f"{name}.log"
        out = open(log, "ab")  # noqa: SIM115
        cmd = list(argv) if role == "root" else ["ip", "netns", "exec", self.host(role).netns, *argv]
        popen = subprocess.Popen(
            cmd, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, env=env, start_new_session=True
        )
        proc = Proc(name, role, popen, log, out)
        self.procs.append(proc)
        return proc

    def signal(self, proc: Proc, sig: int) -> None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.popen.pid, sig)

    def stop(self, proc: Proc, timeout: float = STOP_TIMEOUT) -> int | None:
        """SIGTERM (and SIGCONT, in case it was stopped) to its group, SIGKILL if it outlives `timeout`."""
        if proc.popen.poll() is None:
            self.signal(proc, signal.SIGTERM)
            self.signal(proc, signal.SIGCONT)
            try:
                proc.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                self.signal(proc, signal.SIGKILL)
                proc.popen.wait(10)
        proc.out.close()
        return proc.popen.returncode

    def start_proxy(self, role: str, listen: str, connect: str, connect_netns: str | None = None) -> ProxyControl:
        """A link proxy (tests.multihost.linkproxy) in host `role`, ready when this returns."""
        name = f"proxy-{role}-{len(self.proxies)}"
        control = ProxyControl(str(self.workdir / f"{name}.sock"))
        argv = [sys.executable, "-m", "tests.multihost.linkproxy", "--listen", listen, "--connect", connect]
        argv += ["--control", control.path] + (["--connect-netns", connect_netns] if connect_netns else [])
        proc = self.spawn(role, name, argv)
        deadline = time.monotonic() + READY_TIMEOUT
        while True:
            try:
                control.state()
                break
            except OSError:
                if proc.popen.poll() is not None or time.monotonic() > deadline:
                    raise NetnsError(f"link proxy {name} did not start:\n{proc.tail()}") from None
                time.sleep(0.05)
        self.proxies[name] = control
        return control

    def close(self) -> None:
        """Stop every process (last started first), then remove every namespace and with them the veths."""
        for proc in reversed(self.procs):
            if not proc.out.closed:
                self.stop(proc)
        for name in reversed(self._made):
            _kill_inside(name)
            with contextlib.suppress(NetnsError):
                sh("ip", "netns", "del", name)
        self._made.clear()

    def __enter__(self) -> Topology:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
