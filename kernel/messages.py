"""Operator messages: errors are shown to the operator as one line."""

from __future__ import annotations


def first_line(message: object) -> str:
    """The first non-blank line of ``message`` (an SDK's or cflib's multi-line error text)."""
    lines = [line.strip() for line in str(message).splitlines() if line.strip()]
    return lines[0] if lines else "unknown error"
