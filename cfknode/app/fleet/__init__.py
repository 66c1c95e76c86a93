"""Fleets: several drones in one flight (docs/fleet.md, docs/fleet-ray.md).

- ``flight``: ``cfknode fly --fleet N``, simulated drones in one world and one event loop, and
  ``fly_drones``, the flight any fleet shares;
- ``coordinator``: the separation watch, the fault policy and the ordered landings;
- ``robots``: ``--robots cf1,cf2``, named robots from the robots file;
- ``ray_fleet`` and ``drone_actor``: ``--executor ray``, each drone a Ray actor;
- ``learning``: online learning for every drone, on trainers shared by the drones that train alike;
- ``wake_below``: which drones learn the wake of the one above alone, from the references, and with what;
- ``settings``: the ``fleet:`` config section.

Kept light: the config imports ``settings``, so nothing is imported here.
"""
