"""``cfknode estop --all``: the request to every live flight at once (every drone of a fleet)."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

from cfknode.app.config import ConfigError
from cfknode.safety.estop_mailbox import FlightInfo, FlightScan, MailboxError, check_dir, request, scan_flights


def estop_all(directory: Path, action: str, timeout: float) -> int:
    """Post ``action`` to every live flight in ``directory`` in parallel, so no drone waits for
    another's acknowledgement. 0 when every flight took it, 1 when none runs or one did not."""
    if Path(directory).exists():
        try:
            check_dir(directory, create=False)  # a planted or shared directory could fake flights
        except MailboxError as exc:
            raise ConfigError(str(exc)) from None
    flights = report_skipped(scan_flights(directory)).flights
    if not flights:
        print(f"cfknode estop: no flight is running (mailbox {directory})", file=sys.stderr)
        return 1
    taken: dict[str, str] = {}

    def send(flight: FlightInfo) -> None:
        try:
            taken[flight.id] = "taken" if request(flight, action, timeout=timeout) else "not taken"
        except MailboxError as exc:
            taken[flight.id] = f"not delivered ({exc})"

    threads = [threading.Thread(target=send, args=(f,), daemon=True) for f in flights]
    for th in threads:
        th.start()
    for th in threads:
        th.join(timeout + 1.0)
    failed = 0
    for f in flights:
        verdict = taken.get(f.id, "not taken")
        ok = verdict == "taken"
        failed += not ok
        print(f"cfknode estop: {action} {verdict} by the flight of {f.robot!r} (pid {f.pid}, id {f.id})",
              file=sys.stdout if ok else sys.stderr)
    return 0 if failed == 0 else 1


def report_skipped(scan: FlightScan) -> FlightScan:
    """One line on stderr per presence file that is not a usable flight (it never stops the e-stop)."""
    for line in scan.skipped:
        print(f"cfknode estop: skipped {line}", file=sys.stderr)
    return scan
