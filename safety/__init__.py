"""Host-side safety (docs/design.md#safety): the firmware has no geofence, mocap-loss or battery landing.

- ``supervisor``: the flight's state machine and the radio's only gate (``Supervisor``).
- ``geofence``: the box, its soft margin and the reference clamp.
- ``landing``: the supervisor's own landing reference.
- ``watchdogs``: persistence timers, battery filter, tilt, radio link health.
- ``operator``: Ctrl-C, and the task that hands ``cfknode estop`` requests to the supervisor.
- ``estop_mailbox``: the ``cfknode estop`` mailbox: flight identity, presence, requests;
  ``estop_files``: its small files, read bounded and written atomically.
- ``preflight``: hardware pre-flight checks before the clock starts.
"""

# One import name per module: a checkout on sys.path also exposes this folder as "safety".
if __name__ != "cfknode.safety":
    raise ImportError(f"import cfknode.safety, not {__name__}: this folder is installed as part of cfknode")
