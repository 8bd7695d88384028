"""tests/README.md says where the tests of each module are: ``tests/test_<package>_<module>.py``
by name, or a row of its map. Every module of the package needs one of the two, and every
row must name an existing module and existing test files, so that the map follows the code."""

from __future__ import annotations

import ast
import re
from pathlib import Path

TESTS = Path(__file__).resolve().parent
ROOT = TESTS.parent
PACKAGE = ROOT / "megalut_cli"
README = TESTS / "README.md"
#: A row of the map: | `megalut_cli/<path>.py` | `test_a.py`, `test_b.py` (notes) |
MAP_ROW = re.compile(r"^\|\s*`(megalut_cli/[^`]+\.py)`\s*\|(.*)\|\s*$")
TEST_FILE = re.compile(r"`(test_\w+\.py)`")


def defines_code(path: Path) -> bool:
    """Whether ``path`` has code of its own: any module but an ``__init__.py`` that defines
    no function or class (a docstring, imports, constants)."""
    if path.name != "__init__.py":
        return True
    tree = ast.parse(path.read_text(encoding="utf-8"))
    code = (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)
    return any(isinstance(n, code) for n in tree.body)


def conventional_test_file(module: str) -> str:
    """``megalut_cli/sim/render.py`` -> ``test_sim_render.py``; a package's ``__init__.py``
    -> ``test_<package>.py``."""
    parts = list(Path(module).relative_to("megalut_cli").with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return "test_" + "_".join(parts) + ".py"


def read_map() -> dict[str, list[str]]:
    """The map of tests/README.md: module path -> the test files its row names."""
    rows: dict[str, list[str]] = {}
    for line in README.read_text(encoding="utf-8").splitlines():
        match = MAP_ROW.match(line)
        if match:
            module, cell = match.groups()
            assert module not in rows, f"tests/README.md: two rows for {module}"
            rows[module] = TEST_FILE.findall(cell)
    assert rows, "tests/README.md has no map rows"
    return rows


def package_modules() -> list[str]:
    return sorted(p.relative_to(ROOT).as_posix() for p in PACKAGE.rglob("*.py") if defines_code(p))


def test_the_naming_rule():
    assert conventional_test_file("megalut_cli/sim/render.py") == "test_sim_render.py"
    assert conventional_test_file("megalut_cli/cache.py") == "test_cache.py"
    assert conventional_test_file("megalut_cli/gpu/__init__.py") == "test_gpu.py"


def test_every_module_has_tests_by_name_or_a_map_row():
    rows = read_map()
    by_name = {m for m in package_modules() if (TESTS / conventional_test_file(m)).is_file()}
    missing = [m for m in package_modules() if m not in by_name and m not in rows]
    assert not missing, (
        "modules with neither tests/test_<package>_<module>.py nor a row in the map of "
        f"tests/README.md: {missing}"
    )


def test_every_map_row_names_a_module_and_its_test_files():
    modules = set(package_modules())
    for module, files in read_map().items():
        assert module in modules, f"tests/README.md: {module} is not a module of the package"
        assert files, f"tests/README.md: the row of {module} names no test file"
        for name in files:
            assert (TESTS / name).is_file(), f"tests/README.md: {module}: no tests/{name}"
