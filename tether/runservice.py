"""`tether run SERVICE`: a service process loads this, the runtime and its service, and nothing of the CLI.

`python -m tether run ...` (how the Supervisor starts each service) and the `tether` script's
`tether run ...` (how systemd units and containers do) come here through tether/__main__.py without
importing tether.cli, whose other commands pull in pinocchio, shapely, cryptography, mcap and rich.
A well-formed command line is read here without typer (`read_command_line`): typer and the click it
brings cost a service process some 0.1 s of CPU to import, and typer 0.29 and later check every value
with pydantic (some 7 MB more). Anything else (help, a bad flag) goes to the typer command
(tether.runcommand), which answers it as the whole CLI does.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import signal
import stat
import sys
import threading
import time
import traceback
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from services.runtime import ALL_SERVICES, SWITCH_INTERVAL, ConfigError, NodeSettings

# The shared flags, each followed by its value: all that may stand before `run` for it to come here.
VALUE_FLAGS = ("--robot", "--base-port", "--zenoh-config")
# `error:` in red, as typer's secho and the CLI's rich console show it on a terminal.
RED = "\x1b[31m"
PLAIN = "\x1b[0m"
# A config or world file that cannot be read or is invalid, or an unknown service (the CLI's usage code).
EXIT_USAGE = 2
# Set by tether.supervisor: the read end of a pipe whose write end only the supervising process holds.
# Its end of file says that process is gone, however it went (SIGKILL, a Ctrl-C while it waited for its
# services): the service then stops, instead of serving on orphaned, holding its port for the next `up`.
SUPERVISOR_FD_ENV = "TETHER_SUPERVISOR_FD"
# How long a service whose supervisor is gone gets to stop on SIGTERM before it is killed: what the
# supervisor itself would have waited.
ORPHAN_STOP_WAIT = 10.0

log = logging.getLogger(__name__)


def error(message: str) -> None:
    """`error: ...` on stderr, the word in red on a terminal."""
    word = f"{RED}error:{PLAIN}" if sys.stderr.isatty() else "error:"
    print(f"{word} {message}", file=sys.stderr, flush=True)


def run_service(settings: NodeSettings, service: str, config: Path | None) -> NoReturn:
    """`run`'s work, once the command line is read (by typer or by `read_command_line`): the service
    until its main returns (stopped by SIGINT or SIGTERM), then the process ends (see `leave`) with 0;
    with EXIT_USAGE for an unknown service or a config or world file that cannot be used, with 1 and
    the traceback on stderr for a service that fails (an error naming the port and its holder for a
    port in use), with a SystemExit's own code for one that exits. Under a supervisor it also stops
    when that supervisor is gone (`stop_with_supervisor`). A Ctrl-C before the service takes SIGINT
    over (while it imports) ends it as Python does: no Zenoh session is open yet to abort it."""
    if service not in ALL_SERVICES:
        error(f"unknown service {service!r}; services are {', '.join(ALL_SERVICES)}")
        raise SystemExit(EXIT_USAGE)
    stop_with_supervisor()
    sys.setswitchinterval(SWITCH_INTERVAL)
    module = importlib.import_module(f"services.{service}.main")
    try:
        module.main(settings, config)
    except ConfigError as exc:
        error(str(exc))
        leave(EXIT_USAGE)
    except SystemExit as exc:
        leave(exit_status(exc))
    except Exception as exc:
        # Only a service that loads a world raises this, and has imported its module (and shapely) by then.
        from services.worldmodel import WorldFileError

        if isinstance(exc, WorldFileError):
            error(str(exc))
            leave(EXIT_USAGE)
        if (taken := port_taken(service, exc)) is not None:
            error(taken)
            leave(1)
        traceback.print_exc()
        leave(1)
    leave(0)


def stop_with_supervisor() -> None:
    """When a supervisor started this process ($TETHER_SUPERVISOR_FD), SIGTERM to itself once that
    supervisor is gone, and SIGKILL if it has not stopped ORPHAN_STOP_WAIT later; nothing without one
    (systemd, a shell)."""
    value = os.environ.pop(SUPERVISOR_FD_ENV, None)  # not for the processes this service starts
    if value is None:
        return
    try:
        fd = int(value)
        if not stat.S_ISFIFO(os.fstat(fd).st_mode):
            raise ValueError("not a pipe")
        os.set_inheritable(fd, False)
    except (ValueError, OSError) as exc:
        log.warning(
            "ignoring %s=%r (%s): this service will not stop with its supervisor", SUPERVISOR_FD_ENV, value, exc
        )
        return
    threading.Thread(target=_stop_at_end_of_file, args=(fd,), name="supervisor-watch", daemon=True).start()


def _stop_at_end_of_file(fd: int) -> None:
    try:
        while os.read(fd, 1):  # nobody writes: only the end of file returns
            pass
    except OSError:
        return
    log.warning("the supervisor that started this service is gone: stopping")
    os.kill(os.getpid(), signal.SIGTERM)
    time.sleep(ORPHAN_STOP_WAIT)
    log.warning("still running %g s after SIGTERM: killing itself", ORPHAN_STOP_WAIT)
    os.kill(os.getpid(), signal.SIGKILL)


def port_taken(service: str, exc: Exception) -> str | None:
    """What to say when `exc` is Zenoh failing to listen on a port already in use (another stack, or the
    services of a `tether up` killed before it could stop them): the port and who holds it."""
    text = str(exc)
    where = re.search(r"bound to (\S+):(\d+):", text)
    if "Address already in use" not in text or where is None:
        return None
    from services.procstat import port_holders

    port = int(where.group(2))
    holders = port_holders(port)
    held = ", ".join(f"pid {pid} ({command})" for pid, command in holders) or "a process this user cannot see"
    return f"{service} cannot listen on {where.group(1)}:{port}: the port is in use by {held}"


def exit_status(exc: SystemExit) -> int:
    """The status Python exits with for `exc`: its number, 0 for none, else 1 with its text on stderr."""
    if exc.code is None or isinstance(exc.code, int):
        return exc.code or 0
    print(exc.code, file=sys.stderr)
    return 1


def leave(code: int) -> NoReturn:
    """The service process (or a CLI command's, tether/__main__.py) ends here, its logs and output
    flushed, without the interpreter's finalization. A service's threads outlive its main (the query
    pool's workers are daemon threads, one may wait an hour on a goal); one still inside a Zenoh call
    when Python finalizes is made to exit by the interpreter as it takes the GIL back, and that thread
    exit unwinds through zenoh's Rust frames, which catch it: glibc aborts the process ("FATAL:
    exception not rethrown", SIGABRT). A recorder stopped just after answering a status query died so,
    its recording complete, with -6 for its supervisor (or systemd) to see as a crash. By now the
    service has closed its session and files; nothing else registered at exit has work to do. Output
    that can no longer go anywhere (a closed pipe, no stdout at all) does not change the exit status."""
    try:
        logging.shutdown()
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
    except (OSError, ValueError):
        pass  # the output is gone; the status still tells the supervisor how the service ended
    finally:
        os._exit(code)


def runs_a_service(argv: Sequence[str]) -> bool:
    """Whether `argv` (without the program) is `[--robot R] [--base-port N] [--zenoh-config F] run ...`."""
    i = 0
    while i < len(argv):
        flag, joined, _ = argv[i].partition("=")
        if flag not in VALUE_FLAGS:
            return argv[i] == "run"
        i += 1 if joined else 2
    return False


def read_command_line(argv: Sequence[str]) -> tuple[dict[str, str], str, Path | None] | None:
    """`[--robot R] [--base-port N] [--zenoh-config F] run SERVICE [--config FILE]` (a flag's value
    after `=` or as the next word) as (the shared flags given, the service, the config file); None for
    anything else, for typer to answer as ever: help, an unknown flag, a flag twice, a value that is
    empty or starts with `-`, a base port that is no number (also in $TETHER_BASE_PORT)."""
    words = list(argv)

    def take_flag() -> tuple[str, str] | None:
        flag, joined, value = words.pop(0).partition("=")
        if not joined:
            value = words.pop(0) if words else ""
        return (flag, value) if value and not value.startswith("-") else None

    shared: dict[str, str] = {}
    while words and words[0] != "run":
        taken = take_flag()
        if taken is None or taken[0] not in VALUE_FLAGS or taken[0] in shared:
            return None
        shared[taken[0]] = taken[1]
    if not words:
        return None
    words.pop(0)
    service: str | None = None
    config: str | None = None
    while words:
        if not words[0].startswith("-"):
            if service is not None:
                return None
            service = words.pop(0)
            continue
        taken = take_flag()
        if taken is None or taken[0] != "--config" or config is not None:
            return None
        config = taken[1]
    port = shared.get("--base-port", os.environ.get("TETHER_BASE_PORT") or "0")
    if service is None or not port.isdecimal():
        return None
    return shared, service, None if config is None else Path(config)


def app() -> None:
    """`tether run ...` as the `tether` script and `python -m tether` give it: see `read_command_line`."""
    line = read_command_line(sys.argv[1:])
    if line is None:
        from tether.runcommand import typer_app

        typer_app()
        return
    shared, service, config = line
    try:
        settings = NodeSettings.from_env(
            robot=shared.get("--robot"),
            base_port=int(shared["--base-port"]) if "--base-port" in shared else None,
            zenoh_config=Path(shared["--zenoh-config"]) if "--zenoh-config" in shared else None,
        )
    except ValueError as exc:
        error(str(exc))
        sys.exit(EXIT_USAGE)
    run_service(settings, service, config)
