"""The e-stop mailbox's files: small, private, atomic, never through a link, never blocking.

Reading goes through the project's bounded reader (``cfknode.kernel.bounded_input``): a
regular file only, a size cap, JSON of bounded depth and integers. Writing is a ``mkstemp``
file (mode 0600, unpredictable name) renamed into place, so a link at the target is replaced,
never followed.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

from cfknode.kernel.bounded_input import describe_os_error, file_kind, load_json, open_regular

MAX_BYTES = 4096  # presence and request files are a few hundred bytes


class MailboxError(Exception):
    """The mailbox cannot be used as asked; the message is one line for the user."""


def write_atomic(path: Path, payload: dict[str, Any]) -> int:
    """Write ``payload`` under an unpredictable name beside ``path`` (mode 0600) and rename it
    over ``path``: a symbolic link there is replaced, never followed. Returns the inode.
    A directory at ``path`` cannot be replaced: IsADirectoryError (or another OSError) then."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise MailboxError(f"cannot write in the e-stop mailbox {path.parent}: {describe_os_error(exc)}") from None
    try:
        with os.fdopen(fd, "w") as f:
            json.dump(payload, f)
            inode = os.fstat(f.fileno()).st_ino
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return inode


def read_small(path: Path, owner_only: bool = False) -> bytes:
    """A small regular file's bytes, not through a symbolic link and without blocking.
    ``owner_only``: MailboxError for a file another user owns (it could fake a flight)."""
    f, _ = open_regular(path, MAX_BYTES, MailboxError, "e-stop mailbox file", follow=False)
    with f:
        uid = os.fstat(f.fileno()).st_uid
        if owner_only and uid != os.geteuid():
            raise MailboxError(f"{path} belongs to uid {uid}, not to you (uid {os.geteuid()})")
        data = f.read(MAX_BYTES + 1)
    if len(data) > MAX_BYTES:
        raise MailboxError(f"{path} is larger than {MAX_BYTES} bytes")
    return data


def parse_json(data: bytes, path: Path) -> Any:
    """``data`` as JSON, bounded in depth and integer size; MailboxError naming ``path``."""
    return load_json(data, MailboxError, str(path))


def kind(mode: int) -> str:
    return file_kind(mode)


def pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # exists, owned by someone else
    except (OverflowError, ValueError, OSError):
        return False  # not a pid this system can have
    return True


def proc_start(pid: int) -> str:
    """The process's start time in clock ticks since boot (Linux ``/proc``), "" elsewhere."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
        return fields[19].decode()  # field 22 of the line; fields[0] here is field 3
    except (OSError, IndexError, UnicodeDecodeError):
        return ""
