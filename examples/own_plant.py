"""Fly cfknode's controller, learning online, against a plant this script writes itself.

No cfknode loop and no backend: a point mass 20 % heavier than the controller believes,
with a perfect attitude loop, starts in the air on a 0.5 m circle. Run it from a checkout:
``python examples/own_plant.py``.

The fast adaptation layer (on by default) takes the mass within a fraction of a second. The learner
trains a network on every window, and its gate flies one only if it explains what varies with the
state better than the layer does; a mass is a constant, so here none does (``controller.adaptation:
none`` flies the paper's method, where the networks learn the mass). ``ground_z``: the floor, as the
vehicle starts in the air (the layer does not learn near the floor).
"""

import numpy as np

import cfknode


def main(seconds: float = 10.0) -> dict:
    cfg = cfknode.load_config()
    vehicle, dt = cfg.vehicle, 1.0 / cfg.controller.rate_hz
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q, yaw = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0]), 0.0
    controller = cfknode.Controller(cfg.controller, vehicle, ground_z=0.0)
    errors = []
    with cfknode.online_learning(controller, cfg) as learner:
        for k in range(int(seconds / dt)):
            t = k * dt
            command = controller.step(t, cfknode.StateEstimate(t, p, v, q, yaw), circle)
            target = cfknode.read_setpoint(command.setpoint, vehicle, yaw, dt)  # what the firmware aims for
            q, yaw = np.array(target.quaternion), target.yaw
            body_z = np.array([2 * (q[1] * q[3] + q[0] * q[2]), 2 * (q[2] * q[3] - q[0] * q[1]),
                               1 - 2 * (q[1] ** 2 + q[2] ** 2)])
            v = v + dt * (target.thrust_n / (1.2 * vehicle.mass) * body_z - [0.0, 0.0, vehicle.gravity])
            p = p + dt * v
            errors.append(np.linalg.norm(p - circle.sample(np.array([t + dt])).p[0]))
    result = {"rounds_trained": learner.stats.rounds_trained, "models_accepted": learner.stats.accepted,
              "mass_estimate": controller.adaptation.estimate.thrust_scale if controller.adaptation else None,
              "rms_error_last_2s": float(np.sqrt(np.mean(np.square(errors[-int(2 / dt):]))))}
    print(result)
    return result


if __name__ == "__main__":
    main()
