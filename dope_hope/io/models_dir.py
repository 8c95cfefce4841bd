"""Where an object's mesh file is: the one lookup every command uses.

An object's mesh is, in this order:

1. an explicit file: ``--mesh NAME=PATH``, or ``--mesh PATH`` whose file or folder name
   names the object (:func:`class_of_mesh`), or the only object of the run;
2. the first of these files in a models folder (names match case-insensitively):

   - ``obj_<obj_id:06d>.ply`` (BOP models, millimetres; ``obj_id`` from the HOPE catalog or
     a class named ``obj_NNNNNN``),
   - ``<Name>/textured.obj`` (HOPE release layout, centimetres),
   - ``<Name>.obj``, ``<Name>.ply``,
   - ``<Name>/*.obj``, then ``<Name>/*.ply`` (sorted).

Symmetry declarations beside the mesh are read by :mod:`dope_hope.io.symmetries`; which one
an object uses: :func:`dope_hope.symmetry.resolve.resolve_symmetries`.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

from dope_hope.catalog import get_object, object_names
from dope_hope.errors import ConfigError, InputFileError, UnknownObjectError

_BOP_NAME = re.compile(r"obj_?(\d+)")


def bop_obj_id(class_name: str) -> int | None:
    """BOP obj_id of a class: the HOPE catalog's, or NNNNNN of ``obj_NNNNNN``; else None."""
    m = _BOP_NAME.fullmatch(class_name)
    if m:
        return int(m.group(1))
    try:
        return get_object(class_name).obj_id
    except UnknownObjectError:
        return None


def _catalog_name(name: str) -> str | None:
    try:
        return get_object(name).name
    except UnknownObjectError:
        return None


def class_of_mesh(path: str | os.PathLike) -> str | None:
    """The class a mesh file is of, from its name: the catalog object named by the file stem
    or its folder (case-insensitive; also a ``_``/``-`` separated token, e.g.
    ``hope_ketchup.obj``), or for a BOP ``obj_NNNNNN`` file the catalog object of that id
    (else ``obj_NNNNNN``, the BOP readers' class name); None when the name says nothing."""
    p = Path(path)
    words = [p.stem, p.parent.name]
    words += [t for w in words for t in w.replace("-", "_").split("_")]
    for word in words:
        name = None if not word or word.isdigit() or _BOP_NAME.fullmatch(word) else _catalog_name(word)
        if name is not None:
            return name
    m = re.fullmatch(r"obj_(\d+)", p.stem)
    if m:
        return _catalog_name(m.group(1)) or p.stem
    return None


#: File stems that name no object (a class is then its folder's name).
GENERIC_MESH_STEMS = frozenset({"textured", "textured_simple", "model", "mesh", "object", "scan",
                                "google_16k", "poisson", "meshed", "nontextured", "untitled"})


def mesh_class_name(path: str | os.PathLike) -> str:
    """The class of a mesh given by its file alone: :func:`class_of_mesh` (a catalog object or
    ``obj_NNNNNN``), else the folder's name when the file stem is a generic one
    (:data:`GENERIC_MESH_STEMS`, e.g. ``grocery_objects/Can/textured.obj`` -> "Can"), else the
    file stem (``my_widget.obj`` -> "my_widget")."""
    p = Path(path)
    known = class_of_mesh(p)
    if known is not None:
        return known
    if p.stem.lower() in GENERIC_MESH_STEMS and p.parent.name not in ("", ".", ".."):
        return p.parent.name
    return p.stem


def run_object(name: str, class_names: Sequence[str]) -> str | None:
    """The object of ``class_names`` that ``name`` names (case-insensitive; catalog names
    too), or None when it names none of them."""
    wanted = {(_catalog_name(name) or name).lower(), name.lower()}
    return next((c for c in class_names if c.lower() in wanted or (_catalog_name(c) or c).lower() in wanted),
                None)


def check_run_object(name: str, class_names: Sequence[str], flag: str, value: str) -> str:
    """The object of ``class_names`` named ``name`` in ``flag value`` (``NAME=...``); the one
    rule of a name that is not an object of the run: ConfigError naming the flag, the value
    and the run's objects."""
    found = run_object(name, class_names)
    if found is None:
        raise ConfigError(f"{flag} {value}: {name} is not an object of this run "
                          f"(objects: {', '.join(class_names) or 'none'})")
    return found


def is_named_value(text: str | os.PathLike) -> bool:
    """Whether a ``[NAME=]PATH`` value names its object (``NAME=PATH``): it holds "=" and is not
    itself an existing path."""
    text = os.fspath(text)
    return "=" in text and not Path(text).exists()


def new_object_meshes(mesh_args: Sequence[str | os.PathLike], flag: str = "--mesh") -> dict[str, Path]:
    """``[NAME=]PATH`` values naming objects no model holds yet (new objects for the
    pretrained start) -> {class name: path}, in the order given: NAME, else the file's
    (:func:`mesh_class_name`); or one models folder: each object it holds
    (:func:`objects_in_folder`, its mesh by :func:`find_object_mesh`). ConfigError naming
    ``flag`` for two meshes of one name (names compare case-insensitively), and for a folder
    among several values (one folder, or files)."""
    if len(mesh_args) == 1 and Path(mesh_args[0]).is_dir():
        folder = Path(mesh_args[0])
        return {name: find_object_mesh(name, folder) for name in objects_in_folder(folder)}
    folder = next((os.fspath(a) for a in mesh_args if Path(a).is_dir()), None)
    if folder is not None:
        raise ConfigError(f"{flag} {folder}: a models folder, given with {len(mesh_args) - 1} other {flag} "
                          f"value(s); give either mesh files ({flag} [NAME=]FILE, repeated) or one models folder")
    out: dict[str, Path] = {}
    for text in map(os.fspath, mesh_args):
        name, path = text.split("=", 1) if is_named_value(text) else (mesh_class_name(text), text)
        if not name:
            raise ConfigError(f"{flag} {text}: name the object before '=' (--mesh NAME=PATH)")
        same = next((n for n in out if n.lower() == name.lower()), None)
        if same is not None:
            raise ConfigError(f"{flag} {text}: {out[same]} is {same} too; name each object (--mesh NAME=PATH)")
        out[name] = Path(path)
    return out


def parse_mesh_args(mesh_args: Sequence[str | os.PathLike], class_names: Sequence[str],
                    flag: str = "--mesh", in_order: bool = False) -> dict[str, Path]:
    """``[NAME=]PATH`` values of ``flag`` -> {class name: path} for the run's ``class_names``.

    ``NAME`` must be one of ``class_names`` (:func:`check_run_object`; catalog names match
    case-insensitively). A bare ``PATH`` is the object :func:`class_of_mesh` reads from its
    name (:func:`mesh_class_name`) when that is one of ``class_names``; else, one path for one object, that object;
    else with ``in_order`` (one bare path per object) the object at its position, unless its
    name is another object of the run.

    Raises:
        ConfigError: a NAME that is not an object of the run; a bare path that names another
        object of the run than the one it pairs with; a bare path of an unknown class among
        several classes.
    """
    texts = [os.fspath(a) for a in mesh_args]
    named = [is_named_value(t) for t in texts]
    out: dict[str, Path] = {}
    for i, text in enumerate(texts):
        if named[i]:
            name, path = text.split("=", 1)
            out[check_run_object(name, class_names, flag, text)] = Path(path)
            continue
        mine = run_object(mesh_class_name(text), class_names)
        if in_order and len(texts) == len(class_names) and not any(named):
            if mine is not None and mine != class_names[i]:
                raise ConfigError(f"{flag} {text}: its name says {mine}, but it pairs with {class_names[i]} "
                                  f"(the meshes pair with the objects in order: {', '.join(class_names)}); "
                                  f"write {flag} NAME=PATH")
            out[class_names[i]] = Path(text)
        elif mine is not None:
            out[mine] = Path(text)
        elif len(class_names) == 1 and len(texts) == 1:
            out[class_names[0]] = Path(text)
        else:
            says = class_of_mesh(text)
            why = f"its name says {says}, not an object of this run" if says else "cannot tell which object it is"
            raise ConfigError(f"{flag} {text}: {why}; write {flag} NAME=PATH (objects: {', '.join(class_names)})")
    return out


def _folder_candidates(folder: Path, class_name: str) -> tuple[list[Path], list[str]]:
    """Existing files of the search order for ``class_name`` in ``folder`` (in order), and
    the patterns looked for (for the error message)."""
    entries = {p.name.lower(): p for p in folder.iterdir()}
    name = _catalog_name(class_name) or class_name
    lower = name.lower()
    obj_id = bop_obj_id(name)
    patterns: list[str] = []
    found: list[Path] = []

    def add(key: str, shown: str) -> None:
        patterns.append(shown)
        p = entries.get(key)
        if p is not None and p.is_file():
            found.append(p)

    if obj_id is not None:
        add(f"obj_{obj_id:06d}.ply", f"obj_{obj_id:06d}.ply")
    sub = entries.get(lower)
    patterns.append(f"{name}/textured.obj")
    if sub is not None and sub.is_dir() and (sub / "textured.obj").is_file():
        found.append(sub / "textured.obj")
    add(f"{lower}.obj", f"{name}.obj")
    add(f"{lower}.ply", f"{name}.ply")
    patterns.append(f"{name}/*.obj|ply")
    if sub is not None and sub.is_dir():
        for suffix in (".obj", ".ply"):
            found += sorted(p for p in sub.iterdir() if p.is_file() and p.suffix.lower() == suffix)
    return found, patterns


def find_object_mesh(class_name: str, models_dir: str | os.PathLike | None = None,
                     explicit: Mapping[str, Path] | None = None,
                     required: bool = True) -> Path | None:
    """The mesh file of ``class_name`` (module docstring: explicit file, then models folder).

    Args:
        class_name: the object (catalog name, any case; ``obj_NNNNNN``; or a custom name).
        models_dir: models folder to search, or None.
        explicit: {class name: path} from :func:`parse_mesh_args`.
        required: raise when nothing is found (else return None).

    Raises:
        InputFileError: ``models_dir`` is not a folder; no mesh found while ``required``.
    """
    if explicit:
        name = _catalog_name(class_name) or class_name
        for key in (class_name, name):
            if key in explicit:
                return Path(explicit[key])
    if models_dir is not None:
        folder = Path(models_dir)
        if not folder.is_dir():
            raise InputFileError(folder, "models folder not found")
        found, patterns = _folder_candidates(folder, class_name)
        if found:
            return found[0]
        if required:
            raise InputFileError(folder, f"no mesh for {class_name} (looked for "
                                         + ", ".join(patterns) + ")")
        return None
    if required:
        raise ConfigError(f"no mesh for {class_name}: give --mesh or a models folder")
    return None


def objects_in_folder(models_dir: str | os.PathLike) -> list[str]:
    """Every object a models folder holds (what ``--object all`` means with ``--models-dir``):
    the class of each BOP ``obj_NNNNNN.ply`` (:func:`class_of_mesh`), of each loose
    ``<Name>.obj|ply`` and of each sub-folder holding a mesh (HOPE ``<Name>/textured.obj``);
    sorted by name (case-insensitive; the HOPE release's names sort in catalog order).

    Raises:
        InputFileError: ``models_dir`` is not a folder, or holds no mesh.
    """
    folder = Path(models_dir)
    if not folder.is_dir():
        raise InputFileError(folder, "models folder not found")
    names: set[str] = set()
    for p in folder.iterdir():
        if p.is_file() and p.suffix.lower() in (".obj", ".ply"):
            names.add(class_of_mesh(p) or p.stem)
        elif p.is_dir() and any(f.is_file() and f.suffix.lower() in (".obj", ".ply") for f in p.iterdir()):
            names.add(_catalog_name(p.name) or p.name)
    if not names:
        raise InputFileError(folder, "no mesh in this models folder (looked for obj_NNNNNN.ply, "
                                     "<Name>.obj|ply and <Name>/*.obj|ply)")
    return sorted(names, key=str.lower)


def named_object_values(values: Sequence[str], flag: str, accepted: tuple[str, ...]) -> str | dict[str, str] | None:
    """``flag [NAME=]VALUE`` values -> one VALUE for every object, or {object: VALUE} ("" =
    the others; a catalog NAME in its catalog spelling); None: none given. VALUE is one of
    ``accepted``.

    Raises:
        ConfigError: a VALUE not accepted, or two values for the same object (or for all).
    """
    given: dict[str, str] = {}
    for text in values:
        name, _, value = text.rpartition("=")
        if value not in accepted:
            raise ConfigError(f"{flag} {text}: must be one of {', '.join(accepted)}")
        key = object_names([name])[0] if name and name.lower() != "all" else ""
        if key in given:
            raise ConfigError(f"{flag} {text}: {'every object' if not key else key} already has one")
        given[key] = value
    if not given:
        return None
    return given[""] if list(given) == [""] else given
