"""What the CLI prints: outside text as written (never rich markup), help naming config tables, shell
completion of services and formats, progress on stderr only, one JSON object from --json."""

from __future__ import annotations

import io
import json
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import click
import pytest
import typer
import typer.main
from rich.console import Console
from rich.errors import MarkupError
from typer.testing import CliRunner

from schemas.common import ErrorKind, ServiceError, Stage
from schemas.executor import ExecutePlanFeedback, ExecutePlanResult, FailureKind, PlanStatus, StepResult, StepStatus
from services.runtime import ALL_SERVICES
from tests.unit.test_timeline import write_incident
from tether import cli
from tether.client import MAX_TOLD_ENDS, PlanRun
from tether.completion import complete_plan_format, complete_service, complete_services, one_of
from tether.output import literal

ROOT = Path(__file__).resolve().parents[2]
BACKSLASH = "\\"
HOSTILE = "config [sim] says [/] and [bold red]no[/bold red] \\ [x]"


def flat(text: str) -> str:
    """Console output as one line: rich wraps at the terminal's width and frames help in boxes."""
    return " ".join(text.replace("│", " ").split())


@pytest.fixture
def said(monkeypatch: pytest.MonkeyPatch) -> Iterator[io.StringIO]:
    """What tether.cli prints on its consoles, stderr's and stdout's, wide enough not to wrap."""
    text = io.StringIO()
    screen = Console(file=text, width=400, color_system=None)
    monkeypatch.setattr(cli, "console", screen)
    monkeypatch.setattr(cli, "out", screen)
    yield text


# Outside text prints as written


def test_literal_text_prints_as_written_where_rich_would_eat_it_or_fail() -> None:
    def printed(markup: str) -> str:
        text = io.StringIO()
        Console(file=text, width=400, color_system=None).print(markup)
        return text.getvalue().rstrip("\n")

    assert printed(f"[red]error:[/] [dim]{literal(HOSTILE)}[/]") == f"error: {HOSTILE}"
    assert printed(f"[red]error:[/] {literal('[/] at the start')}") == "error: [/] at the start"
    assert printed(f"[dim]{literal('C:' + BACKSLASH)}[/]") == "C:" + BACKSLASH  # not an escape of [/]
    # What the same text does unescaped: words lost, or an error instead of the message.
    assert printed(f"[red]error:[/] {HOSTILE}") == "error: config  says  and no \\ "
    with pytest.raises(MarkupError, match="nothing to close"):
        printed("[red]error:[/] [/] at the start")


def test_step_feedback_and_a_failure_reason_from_a_service_print_literally(said: io.StringIO) -> None:
    feedback = ExecutePlanFeedback(
        stage=Stage.EXECUTE, step=0, action="pick", label="[sim]", message=HOSTILE, status=StepStatus.FAILED
    )
    cli.print_feedback(feedback)
    with pytest.raises(typer.Exit) as exited:
        cli.world_failed(ServiceError(kind=ErrorKind.INVALID_REQUEST, message=HOSTILE, candidates=["[safety]"]))
    assert exited.value.exit_code == 2
    lines = said.getvalue().splitlines()
    assert lines[0] == f"step [sim] pick: {HOSTILE} failed"
    assert lines[1:] == [f"invalid_request: {HOSTILE}", "known: [safety]"]


def test_a_steps_end_the_feedback_did_not_bring_is_printed_from_the_result(said: io.StringIO) -> None:
    """A fresh-clone run lost the last step's line: its feedback reached `tether send --wait` after the
    result. The result says how every step ended; a step whose end was shown is not shown twice."""
    looked = ["around in the kitchen", "on the kitchen table"]
    ended = [
        StepResult(index=0, action="navigate_to", status=StepStatus.SUCCEEDED, message="at the kitchen"),
        StepResult(
            index=1,
            action="detect",
            status=StepStatus.FAILED,
            message="apple not found",
            failure=FailureKind.PRECONDITION,
            searched=looked,
        ),
    ]
    result = ExecutePlanResult(status=PlanStatus.FAILED, stage=Stage.EXECUTE, reason="step 2 failed", steps=ended)
    seen = [
        ExecutePlanFeedback(stage=Stage.EXECUTE, step=0, action="navigate_to", status=StepStatus.SUCCEEDED),
        ExecutePlanFeedback(stage=Stage.EXECUTE, step=1, action="detect", message="looking", searched=looked),
    ]
    run = PlanRun(goal_id="g", result=result)
    for fb in seen:
        run.heard(fb)
    cli.print_result(run, as_json=False)
    assert said.getvalue().splitlines() == [
        f"step 2 detect: apple not found failed (precondition) (searched: {', '.join(looked)})",
        "failed at stage execute: step 2 failed",
    ]


def test_a_plan_that_runs_for_hours_keeps_what_its_feedback_said_not_the_feedback() -> None:
    """Every feedback of a run was kept in a list until its result came: an hour of a patrol's
    progress grew the CLI (or `tether mcp`) by every message of it."""
    run = PlanRun(goal_id="g")
    run.heard(ExecutePlanFeedback(stage=Stage.SAFETY, message="checking"))
    assert not run.executing
    for n in range(MAX_TOLD_ENDS + 500):
        run.heard(ExecutePlanFeedback(stage=Stage.EXECUTE, step=n % 100, label=str(n), status=StepStatus.SUCCEEDED))
    run.heard(ExecutePlanFeedback(stage=Stage.EXECUTE, step=7, message="driving", status=StepStatus.RUNNING))
    assert run.executing and run.latest is not None and run.latest.message == "driving"
    assert len(run.told_ends) == MAX_TOLD_ENDS and (0, "0") in run.told_ends
    assert not hasattr(run, "feedback"), "the run keeps its feedback"


def test_a_config_error_keeps_the_table_it_names(tmp_path: Path) -> None:
    """The report that found it: `[recorder]` was eaten from "config file bad.toml [recorder]: ..."."""
    bad = tmp_path / "bad.toml"
    bad.write_text("[recorder]\nbogus = 1\n")
    result = CliRunner().invoke(cli.app, ["record", "--config", str(bad), "-o", str(tmp_path / "x.mcap")])
    assert result.exit_code == 2, result.output
    assert f"config file {bad} [recorder]: Object contains unknown field `bogus`" in flat(result.stderr)


RICH_TAG = re.compile(r"(?<!\\)\[[a-z#/@][^\[\]\n]*\]")


def commands(command: Any, path: tuple[str, ...] = ()) -> Iterator[tuple[tuple[str, ...], Any]]:
    """Every command of the CLI with the words that reach it, lazy ones loaded."""
    yield path, command
    if hasattr(command, "list_commands"):
        context = click.Context(command)
        for name in command.list_commands(context):
            yield from commands(command.get_command(context, name), (*path, name))


def test_every_help_shows_the_bracketed_words_it_was_written_with() -> None:
    """`[sim]`, `[recorder]`, ... in a help text or a docstring are config tables, not rich markup."""
    checked = 0
    for path, command in commands(typer.main.get_command(cli.app)):
        texts = [command.help or "", *(getattr(p, "help", None) or "" for p in command.params)]
        written = {tag for text in texts for tag in RICH_TAG.findall(text.replace("\\[", "["))}
        if not written:
            continue
        shown = CliRunner().invoke(cli.app, [*path, "--help"], env={"TERMINAL_WIDTH": "100"})
        assert shown.exit_code == 0, shown.output
        missing = [tag for tag in sorted(written) if tag not in flat(shown.stdout)]
        assert not missing, f"`tether {' '.join(path)} --help` lost {missing}"
        checked += 1
    assert checked >= 3  # up, record, ask at least name config tables


# Exit codes


@pytest.mark.parametrize(
    ("words", "codes"),
    [
        (["estop"], ["Exit 0 once safety's heartbeat shows the latch", "3 when no heartbeat confirmed it"]),
        (["reset"], ["Exit 0 when safety reset it", "2 when safety refused", "3 when safety is unreachable"]),
        (["cancel"], ["Exit 0 when the cancel was requested", "3 when the executor is unreachable"]),
        (["world", "move"], ["Exit 0 moved", "2 refused", "3 no simulator"]),
        (["run"], ["Exit 0 when stopped by SIGINT or SIGTERM", "2 for an unknown service", "1 when the service fails"]),
    ],
)
def test_the_exit_codes_are_in_the_help_of_the_commands_that_act(words: list[str], codes: list[str]) -> None:
    shown = CliRunner().invoke(cli.app, [*words, "--help"], env={"TERMINAL_WIDTH": "100"})
    assert shown.exit_code == 0, shown.output
    for code in codes:
        assert code in flat(shown.stdout), (code, shown.stdout)
    assert ("--json" in shown.stdout) is (words != ["run"])  # every command that acts, but a service


# Shell completion


def test_services_formats_and_backends_complete() -> None:
    assert complete_service("") == list(ALL_SERVICES)
    assert complete_service("r") == ["resolver", "recorder", "ros2", "ros2sim"]
    assert complete_service("x") == []
    assert complete_services("sim,sa") == ["sim,safety"]
    assert complete_services("sim,safety,") == [f"sim,safety,{s}" for s in ALL_SERVICES if s not in ("sim", "safety")]
    assert complete_plan_format("") == ["auto", "json", "yaml", "text"]
    assert complete_plan_format("y") == ["yaml"]
    assert one_of("sim", "ros2")("r") == ["ros2"]


@pytest.mark.parametrize(
    ("line", "candidates"),
    [
        ("tether run sa", ["safety"]),
        ("tether --robot r1 run re", ["resolver", "recorder"]),
        ("tether up --only sim,pa", ["sim,parser"]),
        ("tether up --backend ros", ["ros2", "ros2-standin"]),
        ("tether status --check --service ex", ["executor"]),
        ("tether send plan.json --format ", ["auto", "json", "yaml", "text"]),
        ("tether demo --backend ", ["sim", "ros2"]),
    ],
)
def test_the_shell_completes_service_names_backends_and_formats(line: str, candidates: list[str]) -> None:
    """As bash asks for them (what `tether --install-completion` sets up)."""
    words = line.split(" ")
    env = {"_TETHER_COMPLETE": "complete_bash", "COMP_WORDS": line, "COMP_CWORD": str(len(words) - 1)}
    result = CliRunner().invoke(cli.app, [], env=env, prog_name="tether")
    assert result.exit_code == 0, result.output
    assert result.stdout.split() == candidates


# Progress: on stderr, on a terminal or with --progress


@pytest.fixture(scope="module")
def incident(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_incident(tmp_path_factory.mktemp("recording") / "incident.mcap")


def plain(text: str) -> str:
    """Terminal output without its control sequences, each redraw on a line of its own."""
    return re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", text).replace("\r", "\n")


@pytest.mark.parametrize(
    ("words", "lines"),
    [
        (["inspect", "--json"], ["reading incident.mcap", "building the timeline"]),
        (["recheck", "--json"], ["reading incident.mcap", "rechecking"]),
    ],
)
def test_progress_goes_to_stderr_and_stdout_keeps_one_json_object(
    incident: Path, words: list[str], lines: list[str]
) -> None:
    shown = CliRunner().invoke(cli.app, [words[0], str(incident), *words[1:], "--progress"])
    quiet = CliRunner().invoke(cli.app, [words[0], str(incident), *words[1:]])  # stderr is no terminal here
    assert shown.exit_code == quiet.exit_code, shown.output
    assert json.loads(shown.stdout) == json.loads(quiet.stdout)
    finished = [line for line in plain(shown.stderr).splitlines() if "100%" in line]
    for line in lines:
        assert any(f.startswith(line) for f in finished), f"{line!r} never reached 100%:\n{plain(shown.stderr)}"
    assert not any(line in quiet.stderr for line in lines), quiet.stderr
    hidden = CliRunner().invoke(cli.app, [words[0], str(incident), *words[1:], "--no-progress"])
    assert not any(line in hidden.stderr for line in lines), hidden.stderr


def test_the_cli_and_the_recording_commands_load_rich_progress_only_to_show_progress() -> None:
    code = "import sys, tether.cli, tether.inspect, tether.recordings; print('rich.progress' in sys.modules)"
    child = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert child.stdout.strip() == "False"


def test_each_command_is_listed_on_one_line_of_its_own() -> None:
    """A group's help lists each command by the first paragraph of its docstring, line breaks kept
    (typer's rich mode): a first paragraph wrapped in the source broke the listing mid-sentence."""
    broken = [
        f"tether {' '.join(path)}: {(command.help or '').strip().split(chr(10) * 2)[0]!r}"
        for path, command in commands(typer.main.get_command(cli.app))
        if path and "\n" in (command.short_help or (command.help or "").strip().split("\n\n")[0])
    ]
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize(
    ("estop", "said"),
    [
        ({"latched": True, "source": "operator", "reason": "[red]x[/red]"}, "LATCHED by operator: [red]x[/red]"),
        ({"latched": False, "source": "", "reason": ""}, "clear"),
        ({"latched": None, "source": "", "reason": "no heartbeat from safety"}, "unknown (no heartbeat from safety)"),
    ],
)
def test_status_says_the_latch_in_words(estop: dict[str, Any], said: str) -> None:
    """It said "e-stop: False" for a clear latch and "e-stop: None" with no heartbeat."""
    console = Console(file=io.StringIO(), width=200)
    console.print(f"e-stop: {cli.estop_line(estop)}", highlight=False)
    assert console.file.getvalue().strip() == f"e-stop: {said}"  # type: ignore[attr-defined]
