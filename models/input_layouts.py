"""The networks' input layouts, as a model file's ``architecture.inputs`` names them: the drone's own velocity and
command, and in a fleet the drone above's position (docs/fleet.md#neighbour-input), signed or about its axis."""

from __future__ import annotations

import numpy as np

INPUT_NAMES = ("vx", "vy", "vz", "ax", "ay", "az")
N_IN = len(INPUT_NAMES)
NEIGHBOUR_NAMES = ("nbx", "nby", "nbz")  # neighbour minus self, world frame, m
NEIGHBOUR_INPUT_NAMES = INPUT_NAMES + NEIGHBOUR_NAMES
# A wake network's (``fleet.wake_only``): the drone above's horizontal distance, an input that is always 0 (the
# layout stays as wide as the neighbour input's) and its height above: a rotor's wake is a jet about its axis.
WAKE_NAMES = ("nbr", "nb0", "nbz")
WAKE_INPUT_NAMES = INPUT_NAMES + WAKE_NAMES
INPUT_LAYOUTS = (INPUT_NAMES, NEIGHBOUR_INPUT_NAMES, WAKE_INPUT_NAMES)
# The finest a network resolves the drone above: its inputs are normalised by at least this (m).
NEIGHBOUR_SCALE_FLOOR = 0.05


def about_the_axis(d: np.ndarray) -> np.ndarray:
    """Relative positions of the drone above (n, 3) as a wake network sees them: (horizontal distance, 0, height)."""
    d = np.atleast_2d(d)
    return np.column_stack((np.hypot(d[:, 0], d[:, 1]), np.zeros(d.shape[0]), d[:, 2]))


__all__ = ["INPUT_LAYOUTS", "INPUT_NAMES", "NEIGHBOUR_INPUT_NAMES", "NEIGHBOUR_NAMES", "NEIGHBOUR_SCALE_FLOOR", "N_IN",
           "WAKE_INPUT_NAMES", "WAKE_NAMES", "about_the_axis"]
