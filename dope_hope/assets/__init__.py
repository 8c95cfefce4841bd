"""Weights shipped with the package (the files beside this module; a wheel holds them too)."""
from pathlib import Path

ASSETS_DIR = Path(__file__).resolve().parent
#: The shipped demo model: `dope-hope demo`, and `dope-hope infer` without --weights.
DEMO_WEIGHTS = ASSETS_DIR / "demo_lite.pt"
#: The shipped pretrained lite start: `dope-hope train --init pretrained`, the default start of
#: every new run of its architecture (docs/commands/train.md, "Pretraining").
PRETRAINED_WEIGHTS = ASSETS_DIR / "pretrained_lite.pt"
