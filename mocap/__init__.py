"""Pose sources behind one interface: simulated, motioncapture (hardware), replay."""

# One import name per module: a checkout on sys.path also exposes this folder as "mocap".
if __name__ != "cfknode.mocap":
    raise ImportError(f"import cfknode.mocap, not {__name__}: this folder is installed as part of cfknode")
