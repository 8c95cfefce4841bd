"""Same as ``dope-hope infer``: ``python infer.py IMAGE --weights W``."""
import sys

from dope_hope.cli import main

if __name__ == "__main__":
    sys.exit(main(["infer", *sys.argv[1:]]))
