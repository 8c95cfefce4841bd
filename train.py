"""Same as ``dope-hope train``: ``python train.py --config lite --data DIR --out DIR``."""
import sys

from dope_hope.cli import main

if __name__ == "__main__":
    sys.exit(main(["train", *sys.argv[1:]]))
