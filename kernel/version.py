"""The software version, stamped into every log and model file."""

__version__ = "0.1.0"
