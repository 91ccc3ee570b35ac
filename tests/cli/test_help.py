"""Every command's ``--help`` explains itself: each option shows its default (or that it is
required) and its help text survives rendering whole (no ``[default: 50]`` or ``[view]`` eaten)."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import typer.main

from kvtracker_sdk.cli.app import app
from tests.cli.invoke import invoke


def _commands(group: Any, path: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], Any]]:
    """(name path, command) of every leaf command (typer vendors its own click: duck-typed)."""
    found: list[tuple[tuple[str, ...], Any]] = []
    for name, command in sorted(group.commands.items()):
        if hasattr(command, "commands"):
            found += _commands(command, (*path, name))
        else:
            found.append(((*path, name), command))
    return found


COMMANDS = _commands(typer.main.get_command(app))


def _option_blocks(help_text: str) -> dict[str, str]:
    """Option name -> its whole entry in the rendered help (wrapped lines joined, whitespace
    normalised). An entry starts with a line "  -x, --name ..." and runs to the next one."""
    blocks: dict[str, list[str]] = {}
    names: list[str] = []
    for line in help_text.splitlines():
        if line.startswith("  -"):
            names = re.findall(r"(?<![\w-])(--?[\w][\w-]*)", line.strip().split("  ")[0])
            for name in names:
                blocks[name] = [line]
        elif names and line.startswith("   "):
            for name in names:
                blocks[name].append(line)
        else:
            names = []
    return {name: " ".join(" ".join(lines).split()) for name, lines in blocks.items()}


def test_every_command_is_found() -> None:
    names = {" ".join(path) for path, _ in COMMANDS}
    assert {"track", "demo", "eval", "eval-many", "map info", "export-onnx"} <= names


@pytest.mark.parametrize(("path", "command"), COMMANDS, ids=[" ".join(p) for p, _ in COMMANDS])
def test_every_option_shows_its_default_and_its_whole_help(
    path: tuple[str, ...], command: Any
) -> None:
    result = invoke(*path, "--help")
    assert result.exit_code == 0, result.output
    blocks = _option_blocks(result.stdout)
    problems = []
    for param in command.params:
        if param.param_type_name != "option" or param.name == "help":
            continue
        block = blocks.get(param.opts[0])
        if block is None:
            problems.append(f"{param.opts[0]} missing from --help")
            continue
        if "[default:" not in block and "[required]" not in block:
            problems.append(f"no default: {block!r}")
        if " ".join((param.help or "").split()) not in block:
            problems.append(f"help text altered: {block!r}")
    assert problems == [], f"kvtracker {' '.join(path)} --help: " + "\n".join(problems)


def test_the_extras_are_named() -> None:
    blocks = _option_blocks(invoke("track", "--help").stdout)
    assert "[view] extra" in blocks["--view"]
    assert "[ros] extra" in blocks["--ros2-bag"]


def test_eval_many_help_shows_the_example_manifest_and_the_examples_are_valid() -> None:
    from kvtracker_sdk.scale.manifest import load_manifest

    examples = Path(__file__).parents[2] / "examples" / "manifests"
    shown = invoke("eval-many", "--help").stdout
    block = shown[shown.index("{\n"): shown.index("\n  }\n") + 4]  # the example, indented
    example = examples / "tum_and_simulated.json"
    assert json.loads(block) == json.loads(example.read_text())  # the help shows the file
    assert '"name"' in block and "examples/manifests/simulated.json" in " ".join(shown.split())
    both = load_manifest(example)
    assert [s.source is not None for s in both.sequences] == [True, False]  # real, simulated
    assert both.model is not None and Path(both.model.weights).is_absolute()  # relative to the file
    offline = load_manifest(examples / "simulated.json")
    assert offline.model is None and all(s.simulated for s in offline.sequences)
