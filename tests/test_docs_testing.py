"""docs/testing.md maps the science claims of the docs to the tests that assert them: every
test it names must exist (a renamed or deleted test fails here), and its Set column must say
which set (default or slow) the tests run in. The test files are parsed, not imported."""

from __future__ import annotations

import ast
import re
from functools import cache
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "testing.md"
CLAIM_COLUMNS = ["Claim", "Test", "Set", "Tolerance", "Achieved"]
#: A backticked test reference: `tests/test_x.py::test_name`, optionally `::Class::method`
#: and a parametrize suffix `[id]`.
REFERENCE = re.compile(r"`(tests/[^`\s:]+\.py)((?:::[A-Za-z_]\w*)+)(\[[^`\]]*\])?`")
CELL_SPLIT = re.compile(r"(?<!\\)\|")


def _tables(text: str) -> list[list[list[str]]]:
    """Markdown tables of ``text``: for each, its rows (header first, separator dropped) as
    lists of cells (split on unescaped pipes, stripped)."""
    tables, current = [], []
    for line in [*text.splitlines(), ""]:
        if line.lstrip().startswith("|"):
            cells = [c.strip() for c in CELL_SPLIT.split(line.strip())[1:-1]]
            if not all(re.fullmatch(r":?-+:?", c) for c in cells):
                current.append(cells)
        elif current:
            tables.append(current)
            current = []
    return tables


def _claim_rows() -> list[list[str]]:
    tables = [t for t in _tables(DOC.read_text(encoding="utf-8")) if t[0] and t[0][0] == "Claim"]
    assert tables, "docs/testing.md has no claims table"
    rows = []
    for table in tables:
        assert table[0] == CLAIM_COLUMNS, table[0]
        for row in table[1:]:
            assert len(row) == len(CLAIM_COLUMNS), (
                f"a row of {len(row)} cells (an unescaped |?): {row}"
            )
            rows.append(row)
    return rows


def _is_slow(decorators: list[ast.expr]) -> bool:
    return any(re.search(r"\bmark\.slow\b", ast.unparse(d)) for d in decorators)


def _tests_in(source: str, filename: str = "<test file>") -> dict[str, bool]:
    """Test functions and methods of a test file's source, by name (``name`` and
    ``Class::name``), with whether they are marked slow (on the function, its class or the
    module's ``pytestmark``)."""
    tree = ast.parse(source, filename=filename)
    module_slow = any(
        isinstance(node, ast.Assign)
        and any(isinstance(t, ast.Name) and t.id == "pytestmark" for t in node.targets)
        and _is_slow([node.value])
        for node in tree.body
    )
    found: dict[str, bool] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            found[node.name] = module_slow or _is_slow(node.decorator_list)
        elif isinstance(node, ast.ClassDef):
            class_slow = module_slow or _is_slow(node.decorator_list)
            for item in node.body:
                if isinstance(item, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    slow = class_slow or _is_slow(item.decorator_list)
                    found[f"{node.name}::{item.name}"] = slow
                    found.setdefault(item.name, slow)
    return found


@cache
def _tests_of(path: str) -> dict[str, bool]:
    return _tests_in((ROOT / path).read_text(encoding="utf-8"), path)


def _resolve(path: str, name: str) -> bool:
    """Whether the referenced test is slow; fails if the file or the test is missing."""
    assert (ROOT / path).is_file(), f"docs/testing.md names {path}, which does not exist"
    tests = _tests_of(path)
    assert name in tests, f"docs/testing.md names {path}::{name}, which {path} does not define"
    return tests[name]


def _references(text: str) -> list[tuple[str, str]]:
    return [(m.group(1), m.group(2)[2:]) for m in REFERENCE.finditer(text)]


def test_every_named_test_exists() -> None:
    text = DOC.read_text(encoding="utf-8")
    refs = _references(text)
    assert len(refs) >= 15
    for path, name in refs:
        _resolve(path, name)
    # a backticked `tests/...::...` the pattern does not read is a typo, not a reference
    loose = [
        s for s in re.findall(r"`(tests/[^`]*::[^`]*)`", text) if not REFERENCE.fullmatch(f"`{s}`")
    ]
    assert not loose, loose


def test_claims_table_rows_name_their_tests_and_sets() -> None:
    rows = _claim_rows()
    assert len(rows) >= 15, f"only {len(rows)} claims in docs/testing.md"
    tested = 0
    for claim, test, set_, tolerance, achieved in rows:
        assert claim and tolerance and achieved, (claim, test, set_)
        refs = _references(test)
        if not refs:
            assert test.lower().startswith("none"), (
                f"{claim}: Test names no test and does not say none"
            )
            assert set_ == "—", f"{claim}: no test, but Set is {set_!r}"
            continue
        tested += 1
        kinds = {"slow" if _resolve(path, name) else "default" for path, name in refs}
        expected = " + ".join(k for k in ("default", "slow") if k in kinds)
        assert set_ == expected, f"{claim}: Set is {set_!r}, the tests named run in {expected!r}"
    assert tested >= 15, f"only {tested} claims with a test in docs/testing.md"


@pytest.mark.parametrize(
    ("reference", "parsed"),
    [
        (
            "`tests/test_gpu.py::test_noiseless_stamps_equal_cpu[sersic]`",
            ("tests/test_gpu.py", "test_noiseless_stamps_equal_cpu"),
        ),
        ("`tests/test_x.py::TestThing::test_it[a-1]`", ("tests/test_x.py", "TestThing::test_it")),
        ("`tests/test_x.py`", None),
    ],
)
def test_reference_pattern(reference: str, parsed) -> None:
    refs = _references(reference)
    assert refs == ([parsed] if parsed else [])


SYNTHETIC = """
import pytest

def test_plain():
    pass

@pytest.mark.slow
def test_long():
    pass

@pytest.mark.slow
class TestSlowClass:
    def test_method(self):
        pass

class TestMixed:
    @pytest.mark.slow
    def test_slow_one(self):
        pass

    def test_fast_one(self):
        pass
"""


def test_test_files_are_read_without_importing_them() -> None:
    """Functions and methods are found, and slow is told from default at every level."""
    found = _tests_in(SYNTHETIC)
    assert found == {
        "test_plain": False,
        "test_long": True,
        "TestSlowClass::test_method": True,
        "test_method": True,
        "TestMixed::test_slow_one": True,
        "test_slow_one": True,
        "TestMixed::test_fast_one": False,
        "test_fast_one": False,
    }
    assert all(_tests_in("import pytest\npytestmark = pytest.mark.slow\n" + SYNTHETIC).values())


def test_a_missing_test_is_caught() -> None:
    """A renamed or deleted test, or a deleted module, fails the check."""
    assert _resolve("tests/test_docs_testing.py", "test_every_named_test_exists") is False
    with pytest.raises(AssertionError, match="does not define"):
        _resolve("tests/test_docs_testing.py", "test_that_was_renamed")
    with pytest.raises(AssertionError, match="does not exist"):
        _resolve("tests/test_deleted_module.py", "test_anything")
