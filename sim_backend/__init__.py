"""Simulated Crazyflie: rigid body, onboard firmware behaviour, scenarios, the sim:// cflib link."""

# One import name per module: a checkout on sys.path also exposes this folder as "sim_backend".
if __name__ != "cfknode.sim_backend":
    raise ImportError(f"import cfknode.sim_backend, not {__name__}: this folder is installed as part of cfknode")
