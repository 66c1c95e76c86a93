"""Pose sources behind one interface: simulated, motioncapture (hardware), replay."""
