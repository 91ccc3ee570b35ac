"""Reading small files a user names (camera files, manifests, ground truths, export manifests).

The guarantees of the map reader, for JSON/YAML/text files:

* **regular files only**: a symbolic link is followed to its target, which must be a regular
  file; a FIFO, a socket, a device or a folder is refused at once (``read_user_bytes`` opens
  with ``O_NONBLOCK`` and checks the opened descriptor, so nothing blocks and nothing swapped in
  after a check slips through);
* **a size cap**: the size is checked on the opened descriptor before reading, and at most
  ``max_bytes + 1`` bytes are read (a file growing meanwhile cannot make it read more);
* **bounded structure**: a parsed document nested deeper than ``max_depth`` or with more than
  ``max_values`` values (counting every use of a YAML alias: a 1 kB "billion laughs" document
  expands to billions) is refused before any caller walks it;
* **safe YAML**: PyYAML's safe loader (never constructs Python objects);
* a path that is not a ``str`` or ``os.PathLike`` is a typed error, not a ``TypeError``.

Every failure is the caller's typed error (an ``error`` class of ``kvtracker_sdk.errors``), and
:func:`checked_number` names the field whose value is out of its documented range.
"""

from __future__ import annotations

import json
import math
import os
import stat
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from kvtracker_sdk.errors import KVTrackerError, MissingDependencyError

__all__ = [
    "DEFAULT_MAX_BYTES",
    "DEFAULT_MAX_DEPTH",
    "DEFAULT_MAX_VALUES",
    "checked_number",
    "checked_path",
    "load_user_document",
    "read_user_bytes",
    "read_user_text",
]

DEFAULT_MAX_BYTES = 1 << 20  # camera files and manifests are a few kB; 1 MB is far beyond
DEFAULT_MAX_DEPTH = 32  # the deepest layout we read nests 4 levels
DEFAULT_MAX_VALUES = 100_000  # values in one document, aliases counted as expanded

_NOT_REGULAR = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)
_FLAGS = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0)


def checked_path(
    path: object, error: type[KVTrackerError], *, what: str = "file"
) -> str | os.PathLike[str]:
    """``path`` if it is a ``str`` or ``os.PathLike`` (not bytes, not a number), else ``error``."""
    if isinstance(path, str) or (isinstance(path, os.PathLike) and not isinstance(path, bytes)):
        return path
    raise error(f"{what} path must be a str or a path, got {type(path).__name__} {path!r:.60}")


def read_user_bytes(
    path: object,
    error: type[KVTrackerError],
    *,
    what: str = "file",
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> bytes:
    """The bytes of the regular file ``path`` (symlinks followed), at most ``max_bytes``."""
    target = checked_path(path, error, what=what)
    try:
        fd = os.open(target, _FLAGS)
    except FileNotFoundError as exc:  # also a symbolic link whose target is missing
        raise error(f"{what} {target}: cannot read it: no such file (not a regular file)") from exc
    except (OSError, ValueError) as exc:  # ValueError: a NUL byte in the path
        raise error(f"{what} {target}: cannot read it ({exc})") from exc
    try:
        status = os.fstat(fd)
        if not stat.S_ISREG(status.st_mode):
            kind = next((name for test, name in _NOT_REGULAR if test(status.st_mode)), "special")
            raise error(f"{what} {target}: is {kind}, not a regular file")
        if status.st_size > max_bytes:
            raise error(f"{what} {target}: {status.st_size} bytes, more than the {max_bytes} allowed")
        chunks, total = [], 0
        while total <= max_bytes:  # at most max_bytes + 1 bytes, whatever the file does
            chunk = os.read(fd, min(1 << 20, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
        data = b"".join(chunks)
    except OSError as exc:
        raise error(f"{what} {target}: cannot read it ({exc})") from exc
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # it grew while being read
        raise error(f"{what} {target}: more than the {max_bytes} bytes allowed")
    return data


def read_user_text(
    path: object,
    error: type[KVTrackerError],
    *,
    what: str = "file",
    max_bytes: int = DEFAULT_MAX_BYTES,
) -> str:
    """:func:`read_user_bytes` decoded as UTF-8 (a leading BOM dropped)."""
    data = read_user_bytes(path, error, what=what, max_bytes=max_bytes)
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"{what} {path}: not UTF-8 text ({exc})") from exc


def _check_structure(
    document: Any, error: type[KVTrackerError], what: str, max_depth: int, max_values: int
) -> None:
    """Walk ``document`` without recursion; ``error`` once it is too deep or too large.

    A YAML alias makes one object appear many times; the walk counts every appearance, so an
    alias bomb is stopped after ``max_values`` steps however far it would expand."""
    stack: list[tuple[Any, int]] = [(document, 1)]
    seen = 0
    while stack:
        value, depth = stack.pop()
        seen += 1
        if seen > max_values:
            raise error(f"{what}: more than {max_values} values (or a YAML alias expanding to them)")
        if isinstance(value, Mapping):
            children: Any = [*value.keys(), *value.values()]
        elif isinstance(value, list | tuple):
            children = value
        else:
            continue
        if depth >= max_depth and children:
            raise error(f"{what}: nested deeper than {max_depth} levels")
        stack.extend((child, depth + 1) for child in children)


def _parse_yaml(text: str, error: type[KVTrackerError], what: str) -> Any:
    try:
        import yaml
    except ImportError as exc:
        raise MissingDependencyError.for_extra(
            "yaml", f"reading {what} as YAML needs PyYAML (or write it as JSON)") from exc
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # safe either way; C is faster
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 - a safe loader
    except yaml.YAMLError as exc:
        raise error(f"{what} is not valid YAML: {str(exc)[:300]}") from exc


def load_user_document(
    path: object,
    error: type[KVTrackerError],
    *,
    what: str = "file",
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_depth: int = DEFAULT_MAX_DEPTH,
    max_values: int = DEFAULT_MAX_VALUES,
) -> Any:
    """The JSON (or, for ``.yaml``/``.yml``, YAML) document in ``path``, read with the guarantees
    of the module docstring. Values are not checked: that is the caller's schema."""
    target = checked_path(path, error, what=what)
    text = read_user_text(target, error, what=what, max_bytes=max_bytes)
    label = f"{what} {target}"
    try:
        if Path(target).suffix.lower() in (".yaml", ".yml"):
            document = _parse_yaml(text, error, label)
        else:
            document = json.loads(text)
    except RecursionError as exc:  # nesting deeper than the interpreter's stack
        raise error(f"{label} is not valid JSON/YAML: nested too deeply to read") from exc
    except ValueError as exc:  # JSON syntax; also a number with over 4300 digits
        raise error(f"{label} is not valid JSON: {str(exc)[:300]}") from exc
    _check_structure(document, error, label, max_depth, max_values)
    return document


def checked_number(
    value: Any,
    field: str,
    error: type[KVTrackerError],
    *,
    low: float,
    high: float,
    integer: bool = False,
    low_inclusive: bool = True,
    source: str = "",
) -> float:
    """``value`` as a number in ``[low, high]`` (``(low, high]`` unless ``low_inclusive``),
    or ``error`` naming ``field``. Booleans and strings are not numbers; with ``integer`` the
    value must be whole (an integral float such as ``640.0`` is accepted)."""
    prefix = f"{source}: " if source else ""
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise error(f"{prefix}{field} must be a number, got {type(value).__name__} {value!r:.60}")
    if isinstance(value, float) and not math.isfinite(value):
        raise error(f"{prefix}{field} must be finite, got {value}")
    if integer and isinstance(value, float) and not value.is_integer():
        raise error(f"{prefix}{field} must be a whole number, got {value}")
    above_low = value >= low if low_inclusive else value > low
    if not (above_low and value <= high):
        bracket = "[" if low_inclusive else "("
        shown = f"{value:.6g}" if isinstance(value, float) or abs(value) < 10**15 else "a huge integer"
        raise error(f"{prefix}{field} = {shown} is outside its plausible range {bracket}{low:g}, {high:g}]")
    return float(value)
