"""The root of every exception OpenFusion-Z defines, and the two ways a failure is shown.

Every exception class in the package derives from :class:`OpenFusionError`
(``tests/unit/test_errors.py`` walks the package and checks it). These branches decide what a
user sees:

- :class:`UserError`: something the user can fix: a bad option, value or config, a missing or
  unreadable file, an unknown name. The ``openfusion`` command prints one line that names the
  value and what would be valid, and exits with code 2.
- any other :class:`OpenFusionError`: a failure at run time that is not a bug of this program
  (the bus could not be joined, a service refused or did not answer, a service process died).
  The command prints one line and exits with code 1.
- :class:`Interrupted`: the user stopped the command and it kept its work (the message says
  where): one line, exit code 130.

Anything else that escapes is a bug: the command prints the traceback (exit code 1).

Classes that used to be ``ValueError`` (decode errors, config errors, ...) keep ``ValueError``
as a second base, so code that catches ``ValueError`` around parsing keeps working and pydantic
validators may raise them.

Services never stop for a bad message: their loops catch per message, log with context, count
and go on; only errors at start-up stop a service (``openfusion.bus.runner``).
"""

from __future__ import annotations


class OpenFusionError(Exception):
    """Base of every exception OpenFusion-Z defines."""


class UserError(OpenFusionError):
    """A failure the user can fix (bad input, bad config, missing file): one line, exit code 2."""

    exit_code = 2


class UsageError(UserError, ValueError):
    """A command-line option or argument with a bad value (named in the message)."""


class Interrupted(OpenFusionError):
    """The user stopped the command (Ctrl-C, SIGTERM) and it ended cleanly, keeping what it could
    (the message says what and where): one line, exit code 130."""

    exit_code = 130
