"""The end of `make test`'s output (tests/suite.py): each run's status and every test that failed in it, from
the JUnit XML a real pytest run wrote."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from tests.suite import NO_TESTS, summary

SAMPLE = """
def test_no():
    assert 1 == 2, "one is not two"


def test_yes():
    pass
"""


def test_the_summary_names_each_failed_test_with_its_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "test_sample.py").write_text(SAMPLE)
    report = tmp_path / "report.xml"
    ran = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"--junitxml={report}", "test_sample.py"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert ran.returncode == 1, ran.stdout + ran.stderr
    summary([("tests marked unit", ran.returncode, report), ("tests marked alone", NO_TESTS, tmp_path / "none.xml")])
    summary([("mypy", 0, None)])
    out = capsys.readouterr().out
    assert "tests marked unit: failed (exit 1)\n  FAILED test_sample::test_no: AssertionError: one is not two" in out
    assert "test_yes" not in out
    assert "tests marked alone: no tests\n" in out
    assert "mypy: passed\n" in out
