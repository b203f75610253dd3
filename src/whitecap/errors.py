"""The one exception type users see.

Every stage raises :class:`WhitecapError` for bad input. The CLI prints its
message as a single line (``error: <file>: <field>: <what>``) and exits
non-zero; the Python API lets it propagate.
"""

from __future__ import annotations


class WhitecapError(Exception):
    """A user-facing error: bad input, a missing file, a blow-up."""

    exit_code = 2


class InputError(WhitecapError):
    """A file or a field in it is missing or malformed."""


class SimulationError(WhitecapError):
    """The simulation blew up (NaN, escaping particles)."""

    exit_code = 3


class MissingDependency(WhitecapError):
    """An optional dependency of a stage is not installed."""

    exit_code = 4
