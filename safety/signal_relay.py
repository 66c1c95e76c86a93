"""Stop signals received on a thread of their own, so they act while the loop's thread is stuck.

Python runs a signal handler only on the main thread, between bytecodes: a flight loop
blocked there (a hung call, a long native computation) would never see SIGINT, SIGTERM or
SIGHUP. The C-level handler, though, writes the signal's number to the wakeup fd
(``signal.set_wakeup_fd``) at once, whatever the main thread is doing. ``relay_signals``
points the wakeup fd at a pipe that a small thread reads, and calls ``target.interrupt(name)``
from there. The Python-level handlers it installs do nothing (they exist so that the C handler
is installed). Bytes of other signals are passed on to the wakeup fd that was there before
(asyncio's, for its own handlers).
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from types import FrameType
from typing import Any, Iterator, Protocol

__all__ = ["relay_signals"]

_QUIT = 0  # no signal has number 0: the byte that ends the relay thread


class Interruptible(Protocol):
    def interrupt(self, signal_name: str) -> None: ...


def _ignore(signum: int, frame: FrameType | None) -> None:
    """The Python-level handler: the relay thread has already acted on the signal."""


@contextlib.contextmanager
def relay_signals(target: Interruptible, signals: tuple[signal.Signals, ...]) -> Iterator[bool]:
    """Route ``signals`` to ``target.interrupt(name)`` from a relay thread while the block runs.

    Yields whether the relay is installed (only the main thread may install one; elsewhere the
    signals keep their meaning). The previous handlers and wakeup fd are put back on exit,
    after every signal received so far has been handed to ``target``.
    """
    if threading.current_thread() is not threading.main_thread():
        yield False
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    previous: dict[signal.Signals, Any] = {}
    try:
        old_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    except (ValueError, OSError):
        os.close(read_fd)
        os.close(write_fd)
        yield False
        return
    wanted = {int(s): s.name for s in signals}
    relay = threading.Thread(target=_relay, args=(read_fd, wanted, target, old_fd), name="signal-relay", daemon=True)
    relay.start()
    try:
        for sig in signals:
            previous[sig] = signal.getsignal(sig)
            signal.signal(sig, _ignore)
        yield True
    finally:
        # The wakeup fd first: a signal between the two steps is then never counted twice (by
        # the relay and by a previous handler that acts on it too).
        try:
            signal.set_wakeup_fd(old_fd)
        except (ValueError, OSError):  # the one before is gone (closed out of order): none then
            signal.set_wakeup_fd(-1)
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)
        _write_quit(write_fd)
        relay.join(timeout=5.0)
        os.close(write_fd)
        if not relay.is_alive():  # one stuck in target.interrupt still reads it: leave it open
            os.close(read_fd)


def _write_quit(fd: int) -> None:
    with contextlib.suppress(OSError):
        os.write(fd, bytes([_QUIT]))


def _relay(read_fd: int, wanted: dict[int, str], target: Interruptible, old_fd: int) -> None:
    """Until the quit byte: each wanted signal to ``target``, the others to ``old_fd``."""
    while True:
        try:
            data = os.read(read_fd, 64)
        except InterruptedError:
            continue
        except OSError:
            return
        if not data:
            return
        for signum in data:
            if signum == _QUIT:
                return
            name = wanted.get(signum)
            if name is None:
                if old_fd >= 0:
                    with contextlib.suppress(OSError):
                        os.write(old_fd, bytes([signum]))
                continue
            try:
                target.interrupt(name)
            except Exception:  # noqa: BLE001 - a failing target must not end the relay: later signals still count
                pass
