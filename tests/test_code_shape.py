"""House rules read off the package's source: short functions, and no code that names an issue.

Both walk the source text only (nothing is imported), so they cost a fraction of a CPU-second.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "kvtracker_sdk"
CODE_FOLDERS = ("kvtracker_sdk", "tests", "benchmarks", "examples")
MAX_FUNCTION_LINES = 60  # def line to last line, docstring included; the CLI's commands are exempt

ISSUE_REFERENCE = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)


@functools.cache
def _modules() -> tuple[Path, ...]:
    return tuple(sorted(PACKAGE.rglob("*.py")))


def _code() -> tuple[Path, ...]:
    """Every Python file of the repository's code: the package, tests, benchmarks, examples."""
    return tuple(sorted(p for folder in CODE_FOLDERS for p in (ROOT / folder).rglob("*.py")))


@functools.cache
def _long_functions() -> tuple[tuple[Path, str, int], ...]:
    """(file, function, lines) of every function over the limit, methods and nested ones too."""
    found = []
    for path in _modules():
        pending = list(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)).body)
        while pending:  # statements only: a def is a statement (cheaper than ast.walk)
            node = pending.pop()
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    found.append((path, node.name, lines))
            for name in ("body", "orelse", "finalbody"):
                pending.extend(getattr(node, name, ()))
            for block in (*getattr(node, "handlers", ()), *getattr(node, "cases", ())):
                pending.extend(block.body)
    return tuple(found)


def test_no_function_outside_the_cli_is_over_60_lines() -> None:
    found = [
        f"{path.relative_to(PACKAGE)}:{name} ({lines} lines)"
        for path, name, lines in _long_functions()
        if "cli" not in path.relative_to(PACKAGE).parts
    ]
    assert found == [], f"split these into named pieces of <= {MAX_FUNCTION_LINES} lines: {found}"


def test_no_code_names_an_issue() -> None:
    """Issue numbers go stale: code, tests and docstrings say what and why instead."""
    found = [
        f"{path.relative_to(ROOT)}:{number}: {line.strip()}"
        for path in _code()
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if ISSUE_REFERENCE.search(line)
    ]
    assert found == [], found
