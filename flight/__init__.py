"""Flight: the controller (MPC, model slot, fast adaptation, Mellinger layer), the 400 Hz loop, the estimator,
trajectories, and online learning's flight side."""

# One import name per module: a checkout on sys.path also exposes this folder as "flight".
if __name__ != "cfknode.flight":
    raise ImportError(f"import cfknode.flight, not {__name__}: this folder is installed as part of cfknode")
