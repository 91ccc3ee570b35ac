"""The reader of user-named files: regular files only (symlinks followed), a size cap, bounded
nesting and values, safe YAML, a typed error for anything else."""

from __future__ import annotations

import os
import socket
from pathlib import Path

import pytest

from kvtracker_sdk.errors import ConfigError, SourceError
from kvtracker_sdk.user_files import checked_number, load_user_document, read_user_bytes


def test_only_regular_files_are_read_and_symlinks_are_followed(tmp_path: Path) -> None:
    real = tmp_path / "real.json"
    real.write_text('{"a": 1}')
    (tmp_path / "link.json").symlink_to("real.json")
    assert load_user_document(tmp_path / "link.json", ConfigError) == {"a": 1}
    os.mkfifo(tmp_path / "fifo.json")
    with pytest.raises(ConfigError, match="FIFO"):
        read_user_bytes(tmp_path / "fifo.json", ConfigError)
    with socket.socket(socket.AF_UNIX) as server:
        server.bind(str(tmp_path / "sock"))
        with pytest.raises(ConfigError, match="not a regular file|cannot read"):
            read_user_bytes(tmp_path / "sock", ConfigError)
    with pytest.raises(ConfigError, match="folder"):
        read_user_bytes(tmp_path, ConfigError)
    with pytest.raises(ConfigError, match="path"):
        read_user_bytes(3, ConfigError)


def test_the_size_cap_is_checked_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "big.json"
    path.write_bytes(b" " * 101)
    with pytest.raises(SourceError, match="more than the 100"):
        read_user_bytes(path, SourceError, max_bytes=100)
    assert read_user_bytes(path, SourceError, max_bytes=101) == b" " * 101


def test_nesting_and_value_counts_are_bounded(tmp_path: Path) -> None:
    path = tmp_path / "deep.json"
    path.write_text("[" * 40 + "]" * 40)
    with pytest.raises(ConfigError, match="nested deeper than 32"):
        load_user_document(path, ConfigError)
    path.write_text("[" + ",".join(["1"] * 200) + "]")
    with pytest.raises(ConfigError, match="more than 100 values"):
        load_user_document(path, ConfigError, max_values=100)


def test_checked_number_names_the_field_and_refuses_non_numbers() -> None:
    assert checked_number(640, "width", ConfigError, low=1, high=10_000, integer=True) == 640.0
    for value, message in [(float("nan"), "finite"), ("640", "a number"), (True, "a number"),
                           (10**30, "plausible range"), (0.5, "whole"), ([1], "a number")]:
        with pytest.raises(ConfigError, match=f"width.*{message}"):
            checked_number(value, "width", ConfigError, low=1, high=10_000, integer=True)


def test_the_older_regular_file_reader_refuses_a_folder_with_a_typed_error(tmp_path: Path) -> None:
    """``io/regular_file`` (``--config``, list files) used to raise a raw IsADirectoryError."""
    from kvtracker_sdk.io.files.regular_file import read_regular_text

    with pytest.raises(ConfigError, match="folder"):
        read_regular_text(tmp_path, ConfigError)
