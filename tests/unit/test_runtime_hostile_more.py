"""The shared runtime under what a busy or hostile process or file does to it: decoders first asked for
on several threads at once, config files that are not what a config file is."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from services.parser.config import ParserConfig
from services.runtime import ConfigError, load_config
from tests.sessions import free_ports

ROOT = Path(__file__).resolve().parents[2]
# A fresh interpreter (no decoder built yet) whose threads all ask for the same reply's decoder at once
# and decode with it, as a service's workers do with their first calls; switching threads as often as
# `tether run` has them (runtime.SWITCH_INTERVAL). Before the fix nearly every run died of SIGSEGV.
FIRST_DECODES = """
import sys, threading
from schemas.incidents import IncidentList
from services.runtime import SWITCH_INTERVAL, decoder

sys.setswitchinterval(SWITCH_INTERVAL)
start = threading.Barrier(3)
totals = []

def first_call():
    start.wait()
    totals.append(decoder(IncidentList).decode(b'{"total": 1}').total)

threads = [threading.Thread(target=first_call) for _ in range(3)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
print(totals)
"""
RUNS = 5
WAIT = 5.0
# A service's first uses of struct types on its worker threads, as they come with its first queries:
# once a Node is open, three threads each convert to a type not yet used (a decoder of it never
# built), and three threads build the planner's tool schemas, whose import brings the vocabulary's
# types. Before types were prepared as a Node opens, most runs died of SIGSEGV (msgspec 0.22 hands a
# second thread a half-built type description).
FIRST_USES = """
import sys, threading
import msgspec
from schemas.incidents import IncidentList
from services.planner.node import tool_schemas
from services.runtime import SWITCH_INTERVAL, Node, NodeSettings

node = Node("test", NodeSettings(robot="r1", base_port=int(sys.argv[1])))
sys.setswitchinterval(SWITCH_INTERVAL)
start = threading.Barrier(6)
done = []

def convert():
    start.wait()
    done.append(msgspec.convert({"total": 2}, IncidentList).total)

def tools():
    start.wait()
    done.append(len(tool_schemas()) > 0)

threads = [threading.Thread(target=f) for f in (convert, convert, convert, tools, tools, tools)]
for thread in threads:
    thread.start()
for thread in threads:
    thread.join()
node.close()
print(sorted(map(int, done)))
"""


def test_threads_asking_for_a_decoder_at_once_all_get_a_whole_one() -> None:
    for run in range(RUNS):
        done = subprocess.run(
            [sys.executable, "-c", FIRST_DECODES], cwd=ROOT, capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0, f"run {run}: exit {done.returncode}\n{done.stderr[-2000:]}"
        assert done.stdout.strip() == "[1, 1, 1]", done.stdout


def test_threads_first_using_struct_types_in_an_open_service_do_not_crash_it() -> None:
    for run in range(RUNS):
        base = str(free_ports(9))
        done = subprocess.run(
            [sys.executable, "-c", FIRST_USES, base], cwd=ROOT, capture_output=True, text=True, timeout=60
        )
        assert done.returncode == 0, f"run {run}: exit {done.returncode}\n{done.stderr[-2000:]}"
        assert done.stdout.strip() == "[1, 1, 1, 2, 2, 2]", done.stdout


# Config files as a wrong or hostile hand wrote them: each is refused with a ConfigError naming the file
# and what is wrong, never a traceback of whatever the reading raised.
HOSTILE_CONFIGS = {
    "not UTF-8": (b'[parser]\nvocabulary = "\xff\xfe"\n', "is not UTF-8 text"),
    "arrays nested deep": (b"x = " + b"[" * 100_000 + b"]" * 100_000 + b"\n", "too deeply"),
    "tables nested deep": (b"x = " + b"{a = " * 5000 + b"1" + b"}" * 5000 + b"\n", "too deeply"),
    "an integer of 5000 digits": (b"[parser]\nx = 1" + b"0" * 5000 + b"\n", "too many digits"),
    "a megabyte of comments": (b"# a comment\n" * 100_000, "more than 1048576 bytes; not read"),
}


@pytest.mark.parametrize("name", HOSTILE_CONFIGS)
def test_a_hostile_config_file_is_a_config_error_saying_what_is_wrong(tmp_path: Path, name: str) -> None:
    content, said = HOSTILE_CONFIGS[name]
    path = tmp_path / "tether.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as refused:
        load_config(ParserConfig, path, "parser")
    assert str(path) in str(refused.value) and said in str(refused.value)


@pytest.mark.parametrize("content", ["[saftey]\nforward_timeout = 1.0\n", "forward_timeout = 1.0\n[parser]\n"])
def test_a_table_no_service_reads_is_refused_naming_it(tmp_path: Path, content: str) -> None:
    """A misspelt table ([saftey]) was read by no service: safety ran on its defaults without a word."""
    path = tmp_path / "tether.toml"
    path.write_text(content)
    with pytest.raises(ConfigError) as refused:
        load_config(ParserConfig, path, "parser")
    said = str(refused.value)
    assert str(path) in said and "is no service's table" in said and "[safety]" in said, said
    name = "saftey" if "saftey" in content else "forward_timeout"
    assert f"[{name}]" in said, said


def test_an_unknown_fields_name_is_shown_with_its_control_characters_escaped(tmp_path: Path) -> None:
    path = tmp_path / "tether.toml"
    path.write_text('[parser]\n"\\u001b]0;owned\\u0007" = 1\n')
    with pytest.raises(ConfigError) as refused:
        load_config(ParserConfig, path, "parser")
    assert "\x1b" not in str(refused.value) and "\\x1b]0;owned" in str(refused.value)


def test_a_config_that_is_a_fifo_or_a_device_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "tether.toml"
    os.mkfifo(fifo)
    outcome: list[BaseException | None] = []

    def load() -> None:
        try:
            load_config(ParserConfig, fifo, "parser")
            outcome.append(None)
        except BaseException as exc:
            outcome.append(exc)

    reader = threading.Thread(target=load, daemon=True)
    reader.start()
    reader.join(WAIT)
    if reader.is_alive():  # blocked in the open: a writer's open lets it go
        os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
        reader.join(WAIT)
    assert outcome and isinstance(outcome[0], ConfigError), f"not refused within {WAIT} s: {outcome}"
    assert "not a regular file" in str(outcome[0])
    with pytest.raises(ConfigError, match="not a regular file"):
        load_config(ParserConfig, Path("/dev/zero"), "parser")


def test_a_log_level_logging_does_not_know_is_said_and_the_default_used() -> None:
    script = (
        "import logging\n"
        "from services.runtime import configure_logging\n"
        "configure_logging()\n"
        "logging.getLogger('service').info('serving')\n"
        "logging.getLogger('service').debug('not shown at INFO')\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script],
        cwd=ROOT,
        env={**os.environ, "TETHER_LOG_LEVEL": "LOUD"},
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "TETHER_LOG_LEVEL='LOUD' is not a log level" in done.stderr
    assert "serving" in done.stderr and "not shown" not in done.stderr
