"""Errors meant for the person at the keyboard: the CLI prints them without a traceback."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator


class UserError(Exception):
    """Something the user can fix (a file, an option, a config key); the message says what."""


@contextlib.contextmanager
def user_errors(*kinds: type[Exception]) -> Iterator[None]:
    """The ``kinds`` of error raised inside, as a :class:`UserError` with their message."""
    try:
        yield
    except kinds as err:
        raise UserError(str(err)) from None
