"""One module per ``nanodrift`` command: ``configure(parser)`` declares its options (every attribute
its ``main`` reads), ``main(args)`` returns the exit code; a :class:`nanodrift.errors.UserError` becomes a
one-line message and exit 2. ``daemon/cli.py`` imports a command only when it runs, so ``nanodrift
fit`` never loads zenoh. A command never imports another; what several share is a helper module
(``_name.py``), or lives below the CLI."""
