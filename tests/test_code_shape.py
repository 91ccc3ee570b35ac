"""House rules read off the package's source: short functions, and no code that names an issue.

Both walk the source text only (nothing is imported), so they cost a fraction of a CPU-second.
"""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "kvtracker_sdk"
MAX_FUNCTION_LINES = 60  # def line to last line, docstring included; the CLI's commands are exempt

# Functions still over the limit in the parts being split in parallel (tracking/, io/), as
# (file name, function name): file names, not paths, because those files are moving. The lead
# empties this list when those branches merge; nothing may be added to it.
LONG_FUNCTIONS_BEING_SPLIT = {
    ("tracker.py", "push_frame"),
    ("map_builder.py", "build_map"),
    ("frame_input.py", "prepare"),
    ("map_file.py", "_saved_info"),
}

# The same for modules that still name an issue (file names; same branches, same rule).
MODULES_NAMING_ISSUES_BEING_REWORDED = {"map_file.py"}

ISSUE_REFERENCE = re.compile(r"\bissues?\s*#?\d+", re.IGNORECASE)


@functools.cache
def _modules() -> tuple[Path, ...]:
    return tuple(sorted(PACKAGE.rglob("*.py")))


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
        and (path.name, name) not in LONG_FUNCTIONS_BEING_SPLIT
    ]
    assert found == [], f"split these into named pieces of <= {MAX_FUNCTION_LINES} lines: {found}"


def test_the_long_function_exceptions_are_still_long() -> None:
    """An exception that is no longer needed is removed, so the list only ever shrinks."""
    still_long = {(path.name, name) for path, name, _ in _long_functions()}
    no_longer_long = LONG_FUNCTIONS_BEING_SPLIT - still_long
    assert no_longer_long == set(), f"remove from LONG_FUNCTIONS_BEING_SPLIT: {no_longer_long}"


def test_no_module_names_an_issue() -> None:
    """Issue numbers go stale: code and docstrings say what and why instead."""
    found = [
        f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
        for path in _modules()
        if path.name not in MODULES_NAMING_ISSUES_BEING_REWORDED
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1)
        if ISSUE_REFERENCE.search(line)
    ]
    assert found == [], found


def test_the_issue_exceptions_still_name_an_issue() -> None:
    naming = {p.name for p in _modules() if ISSUE_REFERENCE.search(p.read_text(encoding="utf-8"))}
    reworded = MODULES_NAMING_ISSUES_BEING_REWORDED - naming
    assert reworded == set(), f"remove from MODULES_NAMING_ISSUES_BEING_REWORDED: {reworded}"
