"""Errors a user can cause. The CLI prints them as one line and exits with code 2."""

from __future__ import annotations


class UserError(Exception):
    """Bad input: the message says what was wrong and what is valid."""


class ConfigError(UserError):
    """A config key, value or file that cannot be used."""


class CheckpointError(UserError):
    """A checkpoint that cannot be read."""
