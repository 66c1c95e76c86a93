"""Dynamics models: the nominal quadrotor (numpy, CasADi, torch renderings) and KNODE residuals."""

# One import name per module: a checkout on sys.path also exposes this folder as "models".
if __name__ != "cfknode.models":
    raise ImportError(f"import cfknode.models, not {__name__}: this folder is installed as part of cfknode")
