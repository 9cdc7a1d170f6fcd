"""Errors shown to a user as one line: the command line prints them and exits with code 2."""
from __future__ import annotations


class CliError(Exception):
    """A user-facing failure: printed as one line, exit code 2."""
