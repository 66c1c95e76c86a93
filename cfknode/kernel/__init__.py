"""The kernel: small shared types and protocols every layer may use, and nothing else.

Vehicle parameters, reference samples, attitude setpoints and the firmware's reading of
them, clocks, link status and the settings error. It imports no other part of cfknode.
"""
