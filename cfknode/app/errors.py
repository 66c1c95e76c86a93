"""Bad command-line input: the error every command and benchmark raises, below the CLI that reports it."""

from __future__ import annotations


class UsageError(ValueError):
    """Bad command-line input that argparse cannot catch; exit status 2."""
