"""The README stays a newcomer's page: short, with the install, test and demo commands CI and
users rely on, and no measured number that the benchmarks' tables of record do not hold."""

from __future__ import annotations

import re

from tests.helpers import PROJECT_ROOT

README = (PROJECT_ROOT / "README.md").read_text(encoding="utf-8")


def test_the_readme_is_short_and_keeps_its_commands() -> None:
    assert len(README.splitlines()) <= 300
    lines = README.splitlines()
    assert 'python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 -e ".[dev]"' in lines
    assert "python -m pytest -q" in lines
    first_block = README.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert "download.pytorch.org/whl/cpu" in first_block[0] and first_block[1] == "kvtracker demo --out out/"
    assert "kvtracker-sdk[" not in README  # the package is not on PyPI


def test_every_measured_number_in_the_readme_is_in_a_table_of_record() -> None:
    glance = README.split("## Performance at a glance", 1)[1].split("\n## ", 1)[0]
    record = (PROJECT_ROOT / "benchmarks" / "README.md").read_text(encoding="utf-8")
    numbers = re.findall(r"\d+\.\d+", glance)
    assert len(numbers) >= 6
    for number in numbers:  # as a whole number: 1.94 is not 1.941
        assert re.search(rf"(?<![\d.]){re.escape(number)}(?!\d)", record), number
