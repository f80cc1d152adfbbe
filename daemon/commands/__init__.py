"""One module per ``nanodrift`` command (``daemon/cli.py`` holds the parser and imports a handler only
when its command runs, so ``nanodrift fit`` never loads zenoh). Each module's ``main(args)`` returns
the exit code; a :class:`daemon.errors.UserError` becomes a one-line message and exit 2."""
