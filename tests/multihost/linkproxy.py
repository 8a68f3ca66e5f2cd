"""A TCP proxy standing in for a bad link: a fixed delay, stalls and cuts, steered over a Unix control socket.

    python -m tests.multihost.linkproxy --listen HOST:PORT --connect HOST:PORT --control PATH [--connect-netns NAME]

Run it in the namespace whose clients it serves (`ip netns exec NAME python -m ...`). With
--connect-netns, the connections it opens go out in that other namespace (it enters it after its
listening socket is bound), so one process joins two namespaces: the tests' tap from the root
namespace to the router. TLS passes through untouched: the proxy only moves bytes.

Each accepted connection gets its own upstream connection. Bytes in either direction are held
`delay_ms` (one way, so a round trip takes twice that), and during a stall until the stall ends (a
stall begun while bytes wait holds them too). A cut resets every connection (RST) and refuses new
ones until it is lifted.

The control socket takes one JSON object per line and answers each with one line, the state after it:
    {"delay_ms": 200}   {"stall_s": 1.5}   {"cut": true}   {"cut": false}   {}  (only the state)
The state: delay_ms, cut, stall_from and stall_until (time.time(), 0 before any stall), open,
accepted and refused connection counts, bytes_up and bytes_down.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ctypes
import json
import os
import signal
import socket
import struct
import time
from typing import Any

CLONE_NEWNET = 0x40000000
CHUNK = 64 * 1024
CONNECT_TIMEOUT = 3.0
CONTROL_TIMEOUT = 5.0


def enter_netns(name: str) -> None:
    """Move this thread into network namespace `name` (`ip netns add`'s /run/netns/NAME): sockets opened
    from now on live there; those opened before stay where they were."""
    libc = ctypes.CDLL(None, use_errno=True)
    fd = os.open(f"/run/netns/{name}", os.O_RDONLY)
    try:
        if libc.setns(fd, CLONE_NEWNET) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"cannot enter network namespace {name}: {os.strerror(err)}")
    finally:
        os.close(fd)


def host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not host or not port.isdigit():
        raise argparse.ArgumentTypeError(f"{text!r} is not HOST:PORT")
    return host, int(port)


def reset(writer: asyncio.StreamWriter) -> None:
    """Close with an RST, as a link that breaks does to the far end, not a polite FIN."""
    sock = writer.get_extra_info("socket")
    if sock is not None:
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


class Link:
    """The proxy's state: what the control socket sets and every connection obeys."""

    def __init__(self, upstream: tuple[str, int]) -> None:
        self.upstream = upstream
        self.delay = 0.0
        self.stall_from = 0.0
        self.stall_until = 0.0  # time.time()
        self._stall_until_mono = 0.0
        self.cut = False
        self.conns: set[tuple[asyncio.StreamWriter, asyncio.StreamWriter]] = set()
        self.accepted = 0
        self.refused = 0
        self.bytes = {"up": 0, "down": 0}

    def state(self) -> dict[str, Any]:
        return {
            "delay_ms": round(self.delay * 1000, 3),
            "cut": self.cut,
            "stall_from": self.stall_from,
            "stall_until": self.stall_until,
            "open": len(self.conns),
            "accepted": self.accepted,
            "refused": self.refused,
            "bytes_up": self.bytes["up"],
            "bytes_down": self.bytes["down"],
        }

    def command(self, command: dict[str, Any]) -> dict[str, Any]:
        if "delay_ms" in command:
            self.delay = max(0.0, float(command["delay_ms"])) / 1000
        if "stall_s" in command:
            seconds = max(0.0, float(command["stall_s"]))
            self.stall_from = time.time()
            self.stall_until = self.stall_from + seconds
            self._stall_until_mono = time.monotonic() + seconds
        if "cut" in command:
            self.cut = bool(command["cut"])
            if self.cut:
                for client, server in list(self.conns):
                    reset(client)
                    reset(server)
        return self.state()

    async def serve(self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter) -> None:
        if self.cut:
            self.refused += 1
            reset(client_writer)
            return
        try:
            server_reader, server_writer = await asyncio.wait_for(
                asyncio.open_connection(*self.upstream), CONNECT_TIMEOUT
            )
        except (OSError, TimeoutError):
            self.refused += 1
            reset(client_writer)
            return
        self.accepted += 1
        pair = (client_writer, server_writer)
        self.conns.add(pair)
        pumps = [
            asyncio.create_task(self._pump(client_reader, server_writer, "up")),
            asyncio.create_task(self._pump(server_reader, client_writer, "down")),
        ]
        try:
            # Either side ending ends the connection: Zenoh never half-closes.
            await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in pumps:
                task.cancel()
            self.conns.discard(pair)
            reset(client_writer)
            reset(server_writer)

    async def _pump(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, direction: str) -> None:
        held: asyncio.Queue[tuple[float, bytes] | None] = asyncio.Queue()

        async def read() -> None:
            try:
                while data := await reader.read(CHUNK):
                    held.put_nowait((time.monotonic() + self.delay, data))
            except OSError:
                pass
            finally:
                held.put_nowait(None)

        reading = asyncio.create_task(read())
        try:
            while (item := await held.get()) is not None:
                due, data = item
                # Re-checked after each sleep: a stall that began meanwhile holds these bytes too.
                while (wait := max(due, self._stall_until_mono) - time.monotonic()) > 0:
                    await asyncio.sleep(wait)
                writer.write(data)
                await writer.drain()
                self.bytes[direction] += len(data)
        except OSError:
            pass
        finally:
            reading.cancel()


async def control(link: Link, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while line := await reader.readline():
            try:
                command = json.loads(line)
                if not isinstance(command, dict):
                    raise ValueError("a command is a JSON object")
                reply = link.command(command)
            except (ValueError, TypeError) as exc:
                reply = {"error": f"bad command {line[:200]!r}: {exc}"}
            writer.write(json.dumps(reply).encode() + b"\n")
            await writer.drain()
    finally:
        writer.close()


async def main_async(args: argparse.Namespace) -> None:
    link = Link(args.connect)
    server = await asyncio.start_server(link.serve, *args.listen, reuse_address=True)
    if args.connect_netns:
        enter_netns(args.connect_netns)
    with contextlib.suppress(FileNotFoundError):
        os.unlink(args.control)
    controls = await asyncio.start_unix_server(lambda r, w: control(link, r, w), path=args.control)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)
    print(f"proxy {args.listen[0]}:{args.listen[1]} -> {args.connect[0]}:{args.connect[1]}", flush=True)
    async with server, controls:
        await stop.wait()
    for client, upstream in list(link.conns):
        reset(client)
        reset(upstream)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="linkproxy", description=(__doc__ or "").split("\n")[0])
    parser.add_argument("--listen", type=host_port, required=True, help="HOST:PORT to accept connections on")
    parser.add_argument("--connect", type=host_port, required=True, help="HOST:PORT each connection is passed to")
    parser.add_argument("--control", required=True, help="path of the Unix control socket")
    parser.add_argument("--connect-netns", help="open upstream connections in this network namespace")
    asyncio.run(main_async(parser.parse_args(argv)))


class ProxyControl:
    """The test's side of a running proxy's control socket."""

    def __init__(self, path: str) -> None:
        self.path = path

    def send(self, **command: Any) -> dict[str, Any]:
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
            sock.settimeout(CONTROL_TIMEOUT)
            sock.connect(self.path)
            sock.sendall(json.dumps(command).encode() + b"\n")
            reply = sock.makefile("rb").readline()
        state: dict[str, Any] = json.loads(reply)
        if "error" in state:
            raise ValueError(state["error"])
        return state

    def state(self) -> dict[str, Any]:
        return self.send()

    def delay(self, ms: float) -> dict[str, Any]:
        return self.send(delay_ms=ms)

    def stall(self, seconds: float) -> dict[str, Any]:
        return self.send(stall_s=seconds)

    def cut(self) -> dict[str, Any]:
        return self.send(cut=True)

    def restore(self) -> dict[str, Any]:
        return self.send(cut=False)


if __name__ == "__main__":
    main()
