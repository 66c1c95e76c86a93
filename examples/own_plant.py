"""Fly cfknode's controller, learning online, against a plant this script writes itself.

No cfknode loop and no backend: a point mass 20 % heavier than the controller believes,
with a perfect attitude loop, starts in the air on a 0.5 m circle. Run it from a checkout:
``python examples/own_plant.py``.
"""

import numpy as np

import cfknode


def main(seconds: float = 10.0) -> dict:
    cfg = cfknode.load_config()
    vehicle, dt = cfg.vehicle, 1.0 / cfg.controller.rate_hz
    circle = cfknode.Circle(radius=0.5, speed=0.4, height=1.0)
    start = circle.sample(np.zeros(1))
    p, v, q, yaw = start.p[0].copy(), start.v[0].copy(), np.array([1.0, 0.0, 0.0, 0.0]), 0.0
    controller = cfknode.Controller(cfg.controller, vehicle)
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
    result = {"models_accepted": learner.stats.accepted, "rms_error_last_2s": float(np.sqrt(np.mean(
        np.square(errors[-int(2 / dt):]))))}
    print(result)
    return result


if __name__ == "__main__":
    main()
