"""Errors a user can cause. The CLI prints them as one line and exits with code 2."""

from __future__ import annotations


class UserError(Exception):
    """Bad input: the message says what was wrong and what is valid."""


class ConfigError(UserError):
    """A config key, value or file that cannot be used."""


class CheckpointError(UserError):
    """A checkpoint that cannot be read."""


class NonFiniteError(Exception):
    """A NaN or infinity in a run's rewards, observations, losses or weights: the run stops
    before anything non-finite is saved. Not a UserError (the input was valid): the CLI prints
    the one-line message and exits with code 3. `kept`: the message says what the run kept."""

    kept = False
