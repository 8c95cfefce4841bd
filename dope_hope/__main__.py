"""``python -m dope_hope``: the same as the ``dope-hope`` command."""
import sys

from dope_hope.cli import main

sys.exit(main())
