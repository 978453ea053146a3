"""Errors a user can cause. The CLI prints them as one line and exits with code 2."""

from __future__ import annotations


class UserError(Exception):
    """Bad input: the message says what was wrong and what is valid."""


class ConfigError(UserError):
    """A config key, value or file that cannot be used."""


class CheckpointError(UserError):
    """A checkpoint that cannot be read."""


def note_where(error: BaseException, where: str) -> None:
    """A note on an env's own exception saying where relayrl met it ("relayrl: raised " + `where`):
    its traceback says where in the env's code, not which copy, env step or evaluation. A
    UserError's one line already says what it is about, so it gets none."""
    if not isinstance(error, UserError):
        error.add_note(f"relayrl: raised {where}")


class NonFiniteError(Exception):
    """A NaN or infinity in a run's rewards, observations, losses or weights: the run stops
    before anything non-finite is saved. Not a UserError (the input was valid): the CLI prints
    the one-line message and exits with code 3. `kept`: the message says what the run kept."""

    kept = False
