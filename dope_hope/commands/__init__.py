"""One module per ``dope-hope`` subcommand (see ``dope_hope/cli.py``)."""
