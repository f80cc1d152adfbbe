"""One module per ``nanodrift`` command (``daemon/cli.py`` says how they are run). A command never imports
another; what several share is a helper module (``_name.py``), or lives below the CLI."""
