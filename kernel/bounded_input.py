"""Bounded input: the one way cfknode reads a file it is given (config, model, log, robots, mailbox).

Every reader gets the same rules, and raises its own one-line error type (``error``):
- the path must name a regular file: a FIFO, a device or a link to ``/dev/zero`` is refused
  (opened non-blocking, so a FIFO cannot hang the open, and checked on the open descriptor);
- its size is capped, and the cap is in the message;
- a format with a header reads the header first (``open_regular`` gives the size before any byte);
- parsing is bounded: JSON and YAML nesting depth, integer digits, YAML aliases;
- a value quoted in a message is cut short (``quote``), so a hostile value cannot make the
  message itself the attack (an alias bomb's repr is exponential in its size).
"""

from __future__ import annotations

import json
import os
import reprlib
import stat
from pathlib import Path
from typing import Any, BinaryIO

import yaml

QUOTE_CHARS = 60  # a quoted value in a message is cut to about this many characters
MAX_DEPTH = 32  # nesting of JSON arrays/objects and YAML collections; ours nest 4 deep
MAX_INT_DIGITS = 40  # no setting or metadata field needs more than a 64-bit integer's 20
MAX_YAML_ALIASES = 100  # a config uses a few anchors at most
MAX_NODES = 100_000  # values in a document with every alias expanded; a config has about a thousand

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"), (stat.S_ISLNK, "a symbolic link"))


class _Quote(reprlib.Repr):
    """``reprlib`` bounded in depth and items, and never ``repr`` of a huge integer (which
    itself raises past 4300 digits)."""

    def __init__(self) -> None:
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict, self.maxset = 3, 4, 4, 4, 4
        self.maxstring, self.maxother, self.maxlong = QUOTE_CHARS, QUOTE_CHARS, QUOTE_CHARS

    def repr_int(self, x: int, level: int) -> str:
        if x.bit_length() > 3 * QUOTE_CHARS:
            return f"<an integer of about {int(x.bit_length() * 0.30103)} digits>"
        return super().repr_int(x, level)


_QUOTE = _Quote()


def quote(value: Any) -> str:
    """``repr(value)`` cut short (depth, items and characters): safe for any value in a message."""
    try:
        text = _QUOTE.repr(value)
    except Exception:  # noqa: BLE001 - a message must never fail on the value it quotes
        text = f"<{type(value).__name__}>"
    return text if len(text) <= QUOTE_CHARS + 10 else text[:QUOTE_CHARS] + "..."


def file_kind(mode: int) -> str:
    """What a non-regular file is, in words ("a FIFO", "a directory", ...)."""
    return next((name for test, name in _KINDS if test(mode)), "not a regular file")


def size_text(n: int) -> str:
    for unit, shift in (("GiB", 30), ("MiB", 20), ("KiB", 10)):
        if n >= 1 << shift:
            return f"{n / (1 << shift):g} {unit}"
    return f"{n} bytes"


def open_regular(path: str | Path, max_bytes: int, error: type[Exception], what: str,
                 follow: bool = True, buffering: int = -1) -> tuple[BinaryIO, int]:
    """``path`` opened for reading, with its size, if it is a regular file of at most ``max_bytes``.

    Else ``error`` with one line: "<what> <path>: <problem>" (e.g. "not found").
    ``follow=False`` refuses a symbolic link instead of opening what it points at.
    """
    flags = os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC | (0 if follow else os.O_NOFOLLOW)
    try:
        fd = os.open(path, flags)
    except FileNotFoundError:
        raise error(f"{what} {path}: not found") from None
    except OSError as exc:
        raise error(f"{what} {path}: cannot read it ({describe_os_error(exc)})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise error(f"{what} {path}: {file_kind(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise error(f"{what} {path}: {size_text(st.st_size)} is larger than the cap of {size_text(max_bytes)}")
        return os.fdopen(fd, "rb", buffering=buffering), st.st_size
    except BaseException:
        os.close(fd)
        raise


def read_regular(path: str | Path, max_bytes: int, error: type[Exception], what: str, follow: bool = True) -> bytes:
    """The bytes of a regular file of at most ``max_bytes`` (see ``open_regular``)."""
    f, _ = open_regular(path, max_bytes, error, what, follow)
    with f:
        try:
            data = f.read(max_bytes + 1)
        except OSError as exc:
            raise error(f"{what} {path}: cannot read it ({describe_os_error(exc)})") from None
    if len(data) > max_bytes:  # it grew after the size was checked
        raise error(f"{what} {path}: larger than the cap of {size_text(max_bytes)}")
    return data


def describe_os_error(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


# --- JSON -------------------------------------------------------------------------------------


def _bounded_int(text: str) -> int:
    digits = len(text.lstrip("-"))
    if digits > MAX_INT_DIGITS:
        raise ValueError(f"an integer of {digits} digits (at most {MAX_INT_DIGITS})")
    return int(text)


def load_json(data: bytes | str, error: type[Exception], what: str) -> Any:
    """JSON text parsed with nesting at most ``MAX_DEPTH`` and integers of at most
    ``MAX_INT_DIGITS`` digits; anything else is ``error`` naming ``what``."""
    if json_depth(data) > MAX_DEPTH:
        raise error(f"{what}: nested deeper than {MAX_DEPTH} levels")
    try:
        return json.loads(data, parse_int=_bounded_int)
    except (ValueError, TypeError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        reason = str(exc).split("\n", 1)[0][:QUOTE_CHARS * 2] if "integer of" in str(exc) else "not valid JSON"
        raise error(f"{what}: {reason}") from None


def json_depth(data: bytes | str) -> int:
    """The deepest nesting of brackets outside strings (a linear scan, no recursion)."""
    text = data.decode("utf-8", "replace") if isinstance(data, (bytes, bytearray, memoryview)) else data
    depth = deepest = 0
    in_string = escaped = False
    for ch in text:
        if in_string:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_string = False
        elif ch == '"':
            in_string = True
        elif ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    return deepest


# --- YAML -------------------------------------------------------------------------------------


class _Bound(yaml.YAMLError):
    """A document past one of the bounds above (its message is one short line)."""


class _BoundedLoader(yaml.SafeLoader):
    """PyYAML's safe loader, counting aliases and nesting while it composes the document and
    refusing integers longer than ``MAX_INT_DIGITS`` digits."""

    def __init__(self, stream: str) -> None:
        super().__init__(stream)
        self._aliases = 0
        self._depth = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            self._aliases += 1
            if self._aliases > MAX_YAML_ALIASES:
                raise _Bound(f"more than {MAX_YAML_ALIASES} aliases")
        self._depth += 1
        try:
            if self._depth > MAX_DEPTH:
                raise _Bound(f"nested deeper than {MAX_DEPTH} levels")
            return super().compose_node(parent, index)
        finally:
            self._depth -= 1

    def construct_yaml_int(self, node: Any) -> int:
        digits = sum(ch.isdigit() for ch in str(node.value))
        if digits > MAX_INT_DIGITS:
            raise _Bound(f"an integer of {digits} digits (at most {MAX_INT_DIGITS})")
        return super().construct_yaml_int(node)


_BoundedLoader.add_constructor("tag:yaml.org,2002:int", _BoundedLoader.construct_yaml_int)


def load_yaml(text: str, error: type[Exception], what: str) -> Any:
    """YAML text parsed by the safe loader within the bounds above; ``error`` naming ``what``
    (and the line, where PyYAML knows it) for anything it cannot parse."""
    loader = None
    try:
        loader = _BoundedLoader(text)  # refuses unprintable characters here already
        data = loader.get_single_data()
        if expanded_size(data) > MAX_NODES:  # aliases share objects; anything walking them does not
            raise _Bound(f"more than {MAX_NODES} values once its aliases are expanded")
        return data
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" line {mark.line + 1}" if mark is not None else ""
        if isinstance(exc, _Bound):
            why = f" ({exc})"
        elif isinstance(exc, yaml.reader.ReaderError):
            why = f" (character {exc.character!r} at position {exc.position} is not allowed)"
        else:
            why = ""
        raise error(f"{what}{where} is not valid YAML{why}") from None
    except (ValueError, OverflowError, RecursionError, TypeError) as exc:
        raise error(f"{what} is not valid YAML ({type(exc).__name__})") from None
    finally:
        if loader is not None:
            loader.dispose()


def expanded_size(obj: Any) -> int:
    """How many values ``obj`` holds with shared parts counted at every use (a cycle: unbounded).

    Linear in the distinct objects: each one's size is computed once."""
    sizes: dict[int, int] = {}
    busy: set[int] = set()

    def size(o: Any) -> int:
        if not isinstance(o, (dict, list, tuple)):
            return 1
        key = id(o)
        if key in sizes:
            return sizes[key]
        if key in busy:
            return MAX_NODES + 1  # refers to itself
        busy.add(key)
        items = list(o.keys()) + list(o.values()) if isinstance(o, dict) else o
        total = 1
        for item in items:
            total = min(total + size(item), MAX_NODES + 1)
        sizes[key] = total
        return total

    try:
        return size(obj)
    except RecursionError:
        return MAX_NODES + 1
