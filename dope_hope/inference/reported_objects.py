"""Which of a model's objects a predictor reports (``classes=``), and the mesh each of them gets
(``mesh=``): the names a user gives, matched to the model's channel groups."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from dope_hope.errors import ConfigError
from dope_hope.model.info import ObjectInfo


def select_groups(objects: Sequence[ObjectInfo], classes: Sequence[str] | None,
                  flag: str = "classes") -> list[int]:
    """Channel groups of ``classes`` among a model's ``objects`` (channel order; all when None).

    Names match exactly, else case-insensitively; ConfigError naming ``flag`` and the model's
    objects for a class it does not detect, or for an empty list."""
    names = [o.class_name for o in objects]
    if classes is None:
        return list(range(len(objects)))
    if not len(classes):
        raise ConfigError(f"{flag}: give at least one class (the model's objects: {', '.join(names)})")
    groups = set()
    for c in classes:
        hits = [k for k, n in enumerate(names) if n == c] or \
            [k for k, n in enumerate(names) if n.lower() == str(c).lower()]
        if len(hits) != 1:
            raise ConfigError(f"{flag}: {c!r} is not an object of this model (its objects: {', '.join(names)})")
        groups.add(hits[0])
    return sorted(groups)


def meshes_by_group(mesh: Any, names: Sequence[str]) -> dict[int, Any]:
    """``mesh`` (one mesh, or class name -> mesh) as {index into ``names``: mesh} (``names``: the
    reported objects, a subset of the model's where ``classes`` selects some)."""
    if mesh is None:
        return {}
    if not isinstance(mesh, Mapping):
        if len(names) != 1:
            raise ConfigError(f"mesh: this predictor reports {len(names)} objects ({', '.join(names)}): "
                              "give a mapping class name -> mesh")
        return {0: mesh}
    out: dict[int, Any] = {}
    lower = [n.lower() for n in names]
    for name, m in mesh.items():
        if str(name).lower() not in lower:
            raise ConfigError(f"mesh: {name!r} is not an object this predictor reports ({', '.join(names)})")
        out[lower.index(str(name).lower())] = m
    return out
