"""The kernel: small shared types and protocols every layer may use, and nothing else.

Vehicle parameters, reference samples, attitude setpoints and the firmware's reading of
them, clocks, link status, the settings error, and the bounded reader every given file goes
through (``bounded_input``). It imports no other part of cfknode.
"""
