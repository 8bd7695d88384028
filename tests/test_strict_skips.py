"""The strict-skips check of tests/conftest.py (MEGALUT_STRICT_SKIPS=1): unlisted skips fail."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

TESTS = """
import pytest

def test_runs():
    pass

def test_expected():
    pytest.skip("no frobnicator here")

@pytest.mark.parametrize("k", [1, 2])
def test_listed_by_pattern(k):
    pytest.skip("pattern")

@pytest.mark.skipif(True, reason="a missing package")
def test_unexpected():
    pass

@pytest.mark.xfail(reason="known")
def test_xfail():
    raise AssertionError
"""


@pytest.fixture
def project(pytester: pytest.Pytester) -> pytest.Pytester:
    pytester.makeconftest((Path(__file__).with_name("conftest.py")).read_text())
    pytester.makepyfile(test_some=TESTS)
    (pytester.path / "expected_skips.txt").write_text(
        "# comment\n\ntest_some.py::test_expected # not on this machine\n"
        "test_some.py::test_listed_by_pattern* # parametrized\n"
    )
    return pytester


def test_unlisted_skip_fails_the_session(project: pytest.Pytester, monkeypatch) -> None:
    monkeypatch.setenv("MEGALUT_STRICT_SKIPS", "1")
    result = project.runpytest()
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.assert_outcomes(passed=1, skipped=4, xfailed=1)
    result.stdout.fnmatch_lines(
        [
            "*unexpected skips (MEGALUT_STRICT_SKIPS=1)*",
            "SKIPPED test_some.py::test_unexpected - a missing package",
            "1 skip(s) not listed in *expected_skips.txt*",
        ]
    )
    assert "SKIPPED test_some.py::test_expected" not in result.stdout.str()
    assert "SKIPPED test_some.py::test_listed_by_pattern" not in result.stdout.str()


def test_listed_skips_pass_and_the_check_is_off_by_default(
    project: pytest.Pytester, monkeypatch
) -> None:
    monkeypatch.setenv("MEGALUT_STRICT_SKIPS", "1")
    assert project.runpytest("-k", "not unexpected").ret == pytest.ExitCode.OK
    monkeypatch.delenv("MEGALUT_STRICT_SKIPS")
    result = project.runpytest()
    assert result.ret == pytest.ExitCode.OK
    assert "unexpected skips" not in result.stdout.str()


def test_a_skipped_module_counts(project: pytest.Pytester, monkeypatch) -> None:
    monkeypatch.setenv("MEGALUT_STRICT_SKIPS", "1")
    project.makepyfile(test_mod="import pytest\npytest.importorskip('no_such_module_here')\n")
    result = project.runpytest("-k", "not unexpected")  # the module is the only unlisted skip
    assert result.ret == pytest.ExitCode.TESTS_FAILED
    result.stdout.fnmatch_lines(["SKIPPED test_mod.py - could not import 'no_such_module_here'*"])


def test_a_line_without_reason_is_a_usage_error(project: pytest.Pytester, monkeypatch) -> None:
    monkeypatch.setenv("MEGALUT_STRICT_SKIPS", "1")
    (project.path / "expected_skips.txt").write_text("test_some.py::test_expected\n")
    result = project.runpytest()
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(
        ["*expected_skips.txt:1: expected '<nodeid or pattern> # <reason>'*"]
    )
