"""cfknode's controller as a plug-in for another simulator's ``update(t, state, reference) -> thrust, attitude``.

Many simulators (RotorPy's, for one) call their controller once per physics step with the exact
state and the reference's current point, and want a collective thrust (N) and an attitude
quaternion back; they have no end-of-run hook. ``CfknodePlugin`` adapts ``cfknode.Controller`` to
that: the state is exact and fresh every call (``pose_fresh=True``, the default, is right; a noisy
estimate at a lower rate would pass False between frames), the reference's point is extended over
the MPC's horizon at constant acceleration, and online learning runs with ``start()`` /
``stop()`` (``stop`` also runs at exit). ``ground_z`` is given: the vehicle starts in the air.

Run it from a checkout: ``python examples/simulator_plugin.py``. The "simulator" below is a
point mass 15 % heavier than the controller believes, whose attitude follows the command at once.
"""

import numpy as np

import cfknode
from cfknode import RefSamples


def quat_xyzw_to_wxyz(q: np.ndarray) -> np.ndarray:
    return np.array([q[3], q[0], q[1], q[2]])


class CfknodePlugin:
    """``update(t, state, reference) -> (thrust N, quaternion xyzw)`` around ``cfknode.Controller``.

    ``state``: {"x": position, "v": velocity, "q": quaternion (x, y, z, w)}; ``reference``:
    {"x": position, "x_dot": velocity, "x_ddot": acceleration, "yaw": yaw}.
    """

    def __init__(self, learn: bool = True, ground_z: float = 0.0) -> None:
        self.cfg = cfknode.load_config()
        self.vehicle = self.cfg.vehicle
        self.controller = cfknode.Controller(self.cfg.controller, self.vehicle, ground_z=ground_z)
        self.session = cfknode.online_learning(self.controller, self.cfg) if learn else None
        self.learner = self.session.start() if self.session is not None else None
        self._dt = 1.0 / self.cfg.controller.rate_hz

    def _preview(self, t: float, ref: dict) -> RefSamples:
        # The simulator gives the reference's present only; the MPC looks a horizon ahead.
        times = self.controller.preview_times(t)
        tau = (times - t)[:, None]
        x, v, a = (np.asarray(ref[k], dtype=float) for k in ("x", "x_dot", "x_ddot"))
        return RefSamples(times, x + tau * v + 0.5 * tau**2 * a, v + tau * a, np.tile(a, (times.size, 1)),
                          np.full(times.size, float(ref.get("yaw", 0.0))))

    def update(self, t: float, state: dict, reference: dict) -> tuple[float, np.ndarray]:
        q = quat_xyzw_to_wxyz(np.asarray(state["q"], dtype=float))
        w, x, y, z = q
        yaw = float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))
        est = cfknode.StateEstimate(t, np.asarray(state["x"], float), np.asarray(state["v"], float), q, yaw)
        command = self.controller.step(t, est, self._preview(t, reference))
        target = cfknode.read_setpoint(command.setpoint, self.vehicle, yaw, self._dt)
        qw, qx, qy, qz = target.quaternion
        return target.thrust_n, np.array([qx, qy, qz, qw])

    def stop(self) -> None:
        if self.session is not None:
            self.session.stop()


def main(seconds: float = 8.0) -> dict:
    plugin = CfknodePlugin()
    mass, g = 1.15 * plugin.vehicle.mass, plugin.vehicle.gravity
    dt, radius, speed = plugin._dt, 0.5, 0.5
    w = speed / radius
    p, v, q = np.array([radius, 0.0, 1.0]), np.array([0.0, speed, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])
    errors = []
    for k in range(int(seconds / dt)):
        t = k * dt
        c, s = np.cos(w * t), np.sin(w * t)
        ref = {"x": [radius * c, radius * s, 1.0], "x_dot": [-speed * s, speed * c, 0.0],
               "x_ddot": [-speed * w * c, -speed * w * s, 0.0], "yaw": 0.0}
        thrust, q = plugin.update(t, {"x": p, "v": v, "q": q}, ref)
        qx, qy, qz, qw = q
        body_z = np.array([2 * (qx * qz + qw * qy), 2 * (qy * qz - qw * qx), 1 - 2 * (qx**2 + qy**2)])
        v = v + dt * (thrust / mass * body_z - [0.0, 0.0, g])
        p = p + dt * v
        errors.append(float(np.linalg.norm(p - np.array(ref["x"]))))
    plugin.stop()
    stats = plugin.learner.stats if plugin.learner is not None else None
    result = {"rms_error_last_2s": float(np.sqrt(np.mean(np.square(errors[-int(2 / dt):])))),
              "rounds_trained": stats.rounds_trained if stats else 0,
              "trainer_stopped": plugin.learner is not None and plugin.learner not in plugin.controller.observers}
    print(result)
    return result


if __name__ == "__main__":
    main()
