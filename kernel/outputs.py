"""Where cfknode may write a file: a new path, or one that holds a regular file.

Files are written to a temporary file in the target's directory and moved over it
(``os.replace``). Moved over a device node, a FIFO or a socket, that would replace the node
itself (as root, ``/dev/null`` would become a regular file), so any such target is refused.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"),
          (stat.S_ISFIFO, "a FIFO"), (stat.S_ISSOCK, "a socket"))


def output_problem(path: str | Path) -> str | None:
    """Why ``path`` must not be written (one line), or None: it does not exist, or it (a symlink's
    target included) is a regular file."""
    p = Path(path)
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        if p.is_symlink():
            return f"{p} is a dangling symbolic link; give a file name"
        return None
    except OSError as exc:
        return f"{p}: cannot check ({exc.strerror or exc})"
    if stat.S_ISREG(mode):
        return None
    kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
    return f"{p} is {kind}, not a regular file; give a file name"


__all__ = ["output_problem"]
