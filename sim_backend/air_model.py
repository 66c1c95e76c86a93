"""The realistic plant's own air terms as the MPC's residual model (``sim.air_model``): a bench's ceiling.

A learned model of the state can at best know what the air does as a function of that state. This model
knows it exactly, from the plant's own terms (``aero.py``): the rotor drag and inflow on the velocity, the
ground effect on the height, and in a fleet with ``fleet.neighbour_input`` the wake of the drone above on
the relative position. What no model of the state predicts is left out: the fast random force, the motor
and attitude lags, a mass or thrust-map change (the layer's), and wind.

It is a ``Linearisable`` (flight/model_slot.py) in the MPC's terms: the residual on v' for the state
x = (p, v) and the commanded acceleration u (world frame, gravity excluded). The thrust's direction and the
rotor speeds, which the plant reads from the attitude and the motors, are taken from u + g: the MPC's
point-mass view of the same vehicle. Simulation only (the flight refuses it on hardware).
"""

from __future__ import annotations

import numpy as np

from cfknode.sim_backend.aero import DOWNWASH_TABLE, GROUND_EFFECT_TABLE
from cfknode.sim_backend.settings import AeroTerms

_GROUND_X, _GROUND_Y = (np.array(c) for c in zip(*GROUND_EFFECT_TABLE))
_WAKE_X, _WAKE_Y = (np.array(c) for c in zip(*DOWNWASH_TABLE))
_STEP = 1e-5  # finite-difference step of the linearisation (m, m/s, m/s^2): the terms are smooth at this scale


class AirModel:
    """r(x, u[, nb]) = the plant's rotor drag, inflow, ground effect (and the wake of the drone at ``nb``)."""

    beyond_layer = None  # no stored score: flown on every axis beside the layer

    def __init__(self, terms: AeroTerms, gravity: float, neighbour: bool = False) -> None:
        """``neighbour``: take the drone above's position (a fleet drone's neighbour input) for the wake."""
        self.terms = terms
        self.gravity = gravity
        self._neighbour = neighbour and terms.downwash > 0.0

    @property
    def takes_neighbour(self) -> bool:
        return self._neighbour

    def evaluate(self, x: np.ndarray, u: np.ndarray, nb: np.ndarray | None = None) -> np.ndarray:
        """Residual on v': (n, 3) for x (n, 6), u (n, 3), ``nb`` the neighbour's world position(s) (None: none
        above); (3,) for single vectors."""
        x2, u2 = np.atleast_2d(np.asarray(x, dtype=float)), np.atleast_2d(np.asarray(u, dtype=float))
        out = self._residual(x2, u2, None if nb is None else np.atleast_2d(np.asarray(nb, dtype=float)))
        return out if np.ndim(x) == 2 else out[0]

    def linearise(self, x_nodes: np.ndarray, u_nodes: np.ndarray,
                  nb: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """r ~= c[k] + Jx[k] @ x + Ju[k] @ u at each node (central differences).

        The wake enters as a known force at each node, without its slope in the position: the jet is 6 cm wide,
        and given that slope (up to 20 m/s^2 per m) the MPC steered out of it sideways, 46x the layer's MSE
        on the stacked pair. (A learned neighbour model, residual_np.py, is flown the same way when it sees
        the neighbour alone, ``fleet.wake_only``, and with its slope otherwise.)"""
        x0 = np.asarray(x_nodes, dtype=float)
        u0 = np.asarray(u_nodes, dtype=float)
        n = x0.shape[0]
        # One batched evaluation: the nodes, then each input moved by +-_STEP.
        xs = np.repeat(x0[None], 19, axis=0)
        us = np.repeat(u0[None], 19, axis=0)
        for i in range(6):
            xs[1 + 2 * i, :, i] += _STEP
            xs[2 + 2 * i, :, i] -= _STEP
        for i in range(3):
            us[13 + 2 * i, :, i] += _STEP
            us[14 + 2 * i, :, i] -= _STEP
        r = self._residual(xs.reshape(-1, 6), us.reshape(-1, 3), None).reshape(19, n, 3)
        jx = np.stack([(r[1 + 2 * i] - r[2 + 2 * i]) / (2 * _STEP) for i in range(6)], axis=-1)
        ju = np.stack([(r[13 + 2 * i] - r[14 + 2 * i]) / (2 * _STEP) for i in range(3)], axis=-1)
        c = r[0] - np.einsum("nij,nj->ni", jx, x0) - np.einsum("nij,nj->ni", ju, u0)
        if nb is not None and self._neighbour:
            c[:, 2] += self._wake(x0, np.atleast_2d(np.asarray(nb, dtype=float)))
        return c, jx, ju

    def _residual(self, x: np.ndarray, u: np.ndarray, nb: np.ndarray | None) -> np.ndarray:
        g, t = self.gravity, self.terms
        thrust = u + np.array([0.0, 0.0, g])  # specific thrust vector
        size = np.linalg.norm(thrust, axis=1)
        axis = np.where(size[:, None] > 1e-9, thrust / np.maximum(size, 1e-9)[:, None], np.array([0.0, 0.0, 1.0]))
        # Summed rotor speeds / at hover: thrust goes with speed squared (aero.rotor_speed_ratio).
        speed = np.sqrt(np.maximum(size, 0.0) / g)[:, None]
        v = x[:, 3:6]
        along = np.sum(v * axis, axis=1, keepdims=True)
        r = -t.rotor_drag * speed * (v - along * axis) - t.inflow * speed * along * axis
        if t.ground_effect > 0.0:
            lift = t.ground_effect * np.interp(x[:, 2], _GROUND_X, _GROUND_Y)
            r += (size * lift)[:, None] * axis
        if nb is not None and self._neighbour:
            r[:, 2] += self._wake(x, nb)
        return r

    def _wake(self, x: np.ndarray, nb: np.ndarray) -> np.ndarray:
        """Vertical acceleration [m/s^2] (<= 0) from the wake of the drone at ``nb`` above each state of ``x``."""
        t = self.terms
        d = nb - x[:, 0:3]
        lateral = np.exp(-(d[:, 0] ** 2 + d[:, 1] ** 2) / (2.0 * t.downwash_width ** 2))
        gap = np.where(d[:, 2] > 0.0, d[:, 2], 0.0)
        # The drone above at hover thrust (its weight; the fleet's drones are one vehicle).
        return -t.downwash * self.gravity * np.interp(gap, _WAKE_X, _WAKE_Y, right=0.0) * lateral


__all__ = ["AirModel"]
