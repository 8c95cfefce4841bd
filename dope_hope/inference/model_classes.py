"""Which objects each model of a run reports: ``--classes`` and objects that several models hold.

The rule (``dope-hope infer`` with several ``--weights``): an object is reported by the first
model, in the order given, that holds it; a later model holding it too skips it (one warning
naming both files and the object), so that no object is reported twice. ``--classes`` keeps
a subset of the models' objects.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from dope_hope.errors import ConfigError


def classes_per_model(models: Sequence[tuple[Path, Sequence[str]]], classes: Sequence[str] | None = None,
                      ) -> tuple[list[list[str] | None], list[str]]:
    """Per model, the objects it reports, and the warnings to print.

    Args:
        models: (weights file, its object names in channel-group order) per model, in order.
        classes: ``--classes`` (None or empty: all objects).

    Returns:
        (kept, warnings): kept[i] is None (all of model i's objects), a list of its objects
        (a subset), or [] (nothing: the model is not run); one warning per object held by an
        earlier model too.

    Raises:
        ConfigError: a ``--classes`` name no model holds.
    """
    known = [n for _, names in models for n in names]
    wanted = None
    if classes:
        for c in classes:
            if c.lower() not in {n.lower() for n in known}:
                raise ConfigError(f"--classes: {c!r} is not an object of the model(s) (known: {', '.join(known)})")
        wanted = {c.lower() for c in classes}
    first: dict[str, Path] = {}
    kept: list[list[str] | None] = []
    warnings: list[str] = []
    for weights, names in models:
        mine = []
        for name in names:
            if wanted is not None and name.lower() not in wanted:
                continue
            if name.lower() in first:
                warnings.append(f"{name} is in both {first[name.lower()]} and {weights}: reported from "
                                f"{first[name.lower()]} only (the first --weights holding it)")
                continue
            first[name.lower()] = Path(weights)
            mine.append(name)
        kept.append(None if mine == list(names) else mine)
    return kept, warnings
