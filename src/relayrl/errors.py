"""Errors a user can cause. The CLI prints them as one line and exits with code 2."""

from __future__ import annotations

import numbers


class UserError(Exception):
    """Bad input: the message says what was wrong and what is valid."""


class ConfigError(UserError):
    """A config key, value or file that cannot be used."""


class CheckpointError(UserError):
    """A checkpoint that cannot be read."""


def install(extra: str) -> str:
    """The command that adds one of relayrl's extras, in the README's form (an editable install
    from relayrl's folder)."""
    return f"pip install -e \".[{extra}]\" in relayrl's folder"


def check_count(name: str, value: object, zero: str | None = None) -> int:
    """One line where a count a caller passes (episodes, steps) is not an integer >= 1 (True is
    no count); `zero`: what 0 means, where it is allowed. Returns it as a Python int (a NumPy
    integer's too: Gymnasium refuses those)."""
    # numbers.Integral: NumPy's integers too (a notebook's np.int64), not bools
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < (0 if zero else 1):
        also = f", or 0 {zero}" if zero else ""
        raise UserError(f"{name}={value!r} is not valid; it must be an integer >= 1{also}")
    return int(value)


def one_line(text: str, width: int = 60) -> str:
    """`text` (a value's str or repr) for a one-line message: its whitespace runs, line breaks
    included (an array's repr spans lines), as single spaces, cut to `width` with "..." where longer."""
    text = " ".join(text.split())
    return text if len(text) <= width else text[:width - 3] + "..."


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
