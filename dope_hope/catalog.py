"""The 28 HOPE objects: names, BOP ids, categories and cuboid sizes (a category's symmetry group:
:func:`dope_hope.symmetry.transforms.category_symmetries`).

Sizes are stored in the **mesh frame** (x width, y vertical, z depth), metres. The official
DOPE configs list them in the legacy keypoint frame, e.g. Ketchup [14.8608, 4.3368, 6.4514]
cm; :func:`dope_hope.geometry.legacy_size_to_mesh` maps one to the other. Whenever a mesh is
at hand its own extents take precedence over this table (ARCHITECTURE.md).
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from dope_hope.errors import ConfigError, UnknownObjectError
from dope_hope.geometry import legacy_size_to_mesh

CATEGORIES = ("cylinder", "cuboid", "bottle")

# Legacy-frame cuboid sizes (metres) as published with the official DOPE HOPE configs,
# rounded to 0.1 mm. The three marked "estimate" were not in the published list; they are
# measured-by-eye estimates and are replaced by the mesh's extents whenever one is loaded.
_LEGACY_SIZES_M: dict[str, tuple[tuple[float, float, float], str]] = {
    "AlphabetSoup": ((0.0836, 0.0711, 0.0661), "dope-config"),
    "BBQSauce": ((0.1483, 0.0435, 0.0646), "dope-config"),
    "Butter": ((0.0528, 0.0239, 0.1033), "dope-config"),
    "Cherries": ((0.0580, 0.0709, 0.0661), "dope-config"),
    "ChocolatePudding": ((0.0495, 0.0299, 0.0835), "dope-config"),
    "Cookies": ((0.1672, 0.0402, 0.1227), "dope-config"),
    "Corn": ((0.0580, 0.0709, 0.0661), "dope-config"),
    "CreamCheese": ((0.0510, 0.0237, 0.1032), "estimate"),
    "GranolaBars": ((0.1240, 0.0387, 0.1653), "dope-config"),
    "GreenBeans": ((0.0576, 0.0706, 0.0657), "dope-config"),
    "Ketchup": ((0.148608, 0.043368, 0.064514), "dope-config"),
    "MacaroniAndCheese": ((0.1663, 0.0402, 0.1235), "dope-config"),
    "Mayo": ((0.1479, 0.0410, 0.0645), "dope-config"),
    "Milk": ((0.1904, 0.0733, 0.0722), "dope-config"),
    "Mushrooms": ((0.0333, 0.0708, 0.0659), "dope-config"),
    "Mustard": ((0.1600, 0.0486, 0.0651), "dope-config"),
    "OrangeJuice": ((0.1925, 0.0661, 0.0711), "dope-config"),
    "Parmesan": ((0.1030, 0.0660, 0.0660), "estimate"),
    "Peaches": ((0.0578, 0.0710, 0.0659), "dope-config"),
    "PeasAndCarrots": ((0.0585, 0.0706, 0.0659), "dope-config"),
    "Pineapple": ((0.0576, 0.0696, 0.0657), "dope-config"),
    "Popcorn": ((0.0850, 0.0383, 0.1265), "dope-config"),
    "Raisins": ((0.1232, 0.0398, 0.0859), "dope-config"),
    "SaladDressing": ((0.1474, 0.0437, 0.0640), "dope-config"),
    "Spaghetti": ((0.0498, 0.0285, 0.2499), "dope-config"),
    "TomatoSauce": ((0.0828, 0.0702, 0.0665), "dope-config"),
    "Tuna": ((0.0334, 0.0855, 0.0848), "estimate"),
    "Yogurt": ((0.0537, 0.0680, 0.0679), "dope-config"),
}

_CATEGORY_OF: dict[str, str] = {}
for _name in ("Mushrooms Tuna Yogurt Peaches Pineapple Cherries Corn GreenBeans "
              "PeasAndCarrots TomatoSauce AlphabetSoup Parmesan").split():
    _CATEGORY_OF[_name] = "cylinder"
for _name in ("ChocolatePudding Butter CreamCheese Raisins Popcorn Milk OrangeJuice "
              "GranolaBars MacaroniAndCheese Cookies Spaghetti").split():
    _CATEGORY_OF[_name] = "cuboid"
for _name in "SaladDressing Mayo BBQSauce Ketchup Mustard".split():
    _CATEGORY_OF[_name] = "bottle"

_DISPLAY_NAMES = {
    "AlphabetSoup": "Alphabet Soup", "BBQSauce": "BBQ Sauce", "ChocolatePudding": "Chocolate Pudding",
    "CreamCheese": "Cream Cheese", "GranolaBars": "Granola Bars", "GreenBeans": "Green Beans",
    "MacaroniAndCheese": "Macaroni and Cheese", "OrangeJuice": "Orange Juice",
    "PeasAndCarrots": "Peas and Carrots", "SaladDressing": "Salad Dressing",
    "TomatoSauce": "Tomato Sauce",
}

#: The mesh frame's vertical axis for the HOPE meshes (the bottle's / can's axis).
VERTICAL_AXIS = np.array([0.0, 1.0, 0.0])


@dataclass(frozen=True)
class HopeObject:
    """One HOPE object.

    Attributes:
        name: release name, e.g. "Ketchup" (the class name in annotations).
        obj_id: BOP object id, 1..28.
        display_name: human-readable name.
        category: "cylinder", "cuboid" or "bottle" (the HOPE paper's grouping).
        size: (3,) cuboid extents in the mesh frame, metres.
        size_source: "dope-config" (published) or "estimate".
        diameter: largest distance between two cuboid corners (the box diagonal), metres;
            an upper bound of the mesh diameter, which replaces it when a mesh is loaded.
    """

    name: str
    obj_id: int
    display_name: str
    category: str
    size: tuple[float, float, float]
    size_source: str

    @property
    def size_array(self) -> np.ndarray:
        """(3,) float, metres."""
        return np.array(self.size)

    @property
    def diameter(self) -> float:
        """Box diagonal, metres."""
        return float(np.linalg.norm(self.size))


def _build_catalog() -> tuple[HopeObject, ...]:
    objects = []
    for obj_id, name in enumerate(sorted(_LEGACY_SIZES_M), start=1):
        legacy, source = _LEGACY_SIZES_M[name]
        size = tuple(float(v) for v in legacy_size_to_mesh(np.array(legacy)))
        objects.append(HopeObject(name, obj_id, _DISPLAY_NAMES.get(name, name),
                                  _CATEGORY_OF[name], size, source))  # type: ignore[arg-type]
    return tuple(objects)


#: All 28 objects, ordered by BOP obj_id (alphabetical release names).
HOPE_OBJECTS: tuple[HopeObject, ...] = _build_catalog()
_BY_NAME = {o.name.lower(): o for o in HOPE_OBJECTS}


def get_object(name_or_id: str | int) -> HopeObject:
    """Look an object up by release name (case-insensitive) or BOP obj_id."""
    if isinstance(name_or_id, (int, np.integer)) or str(name_or_id).isdigit():
        idx = int(name_or_id)
        if 1 <= idx <= len(HOPE_OBJECTS):
            return HOPE_OBJECTS[idx - 1]
        raise UnknownObjectError(f"no HOPE object has obj_id {idx} (valid: 1..{len(HOPE_OBJECTS)})")
    key = str(name_or_id).lower().replace("_", "").replace(" ", "")
    if key in _BY_NAME:
        return _BY_NAME[key]
    raise UnknownObjectError(
        f"unknown HOPE object {name_or_id!r}; known: {', '.join(o.name for o in HOPE_OBJECTS)}")


def object_names(names: Sequence[str], all_objects: Sequence[str] | None = None) -> list[str]:
    """The objects a command names (``--object A B ...``): HOPE names in their catalog spelling
    (any case), other names (custom objects, ``obj_NNNNNN``) as given, "all" for
    ``all_objects`` (the objects of a models folder) or, when None, the 28 HOPE objects; in
    the order given.

    Raises:
        ConfigError: no name, or one object twice (names compare case-insensitively).
    """
    out: list[str] = []
    for name in names:
        if str(name).lower() == "all":
            out += list(all_objects) if all_objects is not None else [o.name for o in HOPE_OBJECTS]
            continue
        try:
            out.append(get_object(name).name)
        except UnknownObjectError:
            out.append(str(name))
    if not out:
        raise ConfigError("--object: no object named")
    seen: set[str] = set()
    for name in out:
        if name.lower() in seen:
            raise ConfigError(f"--object: {name} is named twice")
        seen.add(name.lower())
    return out
