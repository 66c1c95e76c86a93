"""Flight core: clock, 400 Hz loop, estimator, trajectories, MPC, Mellinger layer, radio, log."""
