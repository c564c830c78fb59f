"""Errors every posegrid process may raise for its user, kept apart from the command line so that no runtime
module imports services.cli."""

from __future__ import annotations

#: the exit code of a process that refused its input or options (:class:`UsageError`); the launcher never restarts it
USAGE_EXIT = 2


class UsageError(Exception):
    """A command-line argument or setting is wrong; the message says what and how to fix it (exit 2)."""
