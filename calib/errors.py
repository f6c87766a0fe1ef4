"""The project's own error types.

Every failure a user can cause (a bad file, a bad parameter, an infeasible scenario) is raised as an
:class:`IptmError` whose message is one line saying what went wrong, where, and how to fix it. The command
line and the dashboard catch this type and show the message; anything else is a bug.
"""
from __future__ import annotations


class IptmError(Exception):
    """Base class: a user-facing error with a one-line message."""


class LogFormatError(IptmError):
    """A log file cannot be read: corrupt, truncated, unknown unit, bad time base...

    Parameters
    ----------
    path : str
        The file.
    problem : str
        What is wrong.
    where : str, optional
        Line, message, frame or channel where the problem is.
    hint : str, optional
        How to fix it.
    """

    def __init__(self, path, problem: str, where: str | None = None, hint: str | None = None):
        self.path = str(path)
        self.problem = problem
        self.where = where
        self.hint = hint
        msg = f"{self.path}"
        if where:
            msg += f" ({where})"
        msg += f": {problem}"
        if hint:
            msg += f" - {hint}"
        super().__init__(msg)


class MissingChannelsError(IptmError):
    """A log lacks channels that a fit or a cycle extraction needs."""

    def __init__(self, missing, purpose: str, source: str = ""):
        self.missing = list(missing)
        self.purpose = purpose
        src = f"{source}: " if source else ""
        super().__init__(
            f"{src}cannot {purpose}: missing channel(s) {', '.join(self.missing)}"
            " - log them, or map an existing column to them (see `iptm ingest --help`)"
        )


class ParameterError(IptmError):
    """A parameter file or value is invalid (unknown name, wrong unit, out of bounds...)."""


class ScenarioError(IptmError):
    """A scenario is invalid or infeasible."""


class ResultFileError(IptmError):
    """A saved result (simulation, calibration, DP outcome) cannot be read or written: not one, of another
    kind or a newer format version, damaged."""


class IptmWarning(UserWarning):
    """Base class: something the user should know that does not stop the work."""


class LogDamageWarning(IptmWarning):
    """A damaged log was read as far as it could be; the message says what was lost."""


class ChannelLossWarning(IptmWarning):
    """A channel lost samples where it entered (non-finite or physically impossible values); the message names
    each channel, how many it lost and when."""
