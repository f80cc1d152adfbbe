"""Errors meant for the person at the keyboard: the CLI prints them without a traceback."""


class UserError(Exception):
    """Something the user can fix (a file, an option, a config key); the message says what."""
