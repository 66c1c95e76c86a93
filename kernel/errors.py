"""The one error type for settings that cannot be flown."""

from __future__ import annotations


class ConfigError(ValueError):
    """A configuration problem, with a one-line message naming the key or file."""
