"""The models of one `dope-hope infer` run: a :class:`~dope_hope.inference.predictor.DopePredictor`
per model file (its objects, its meshes, the classes it reports) and, on a stream, the
:class:`~dope_hope.inference.tracking.PoseTracker` over them.

An object that several model files hold is reported by the first of them only
(:func:`kept_classes`), never twice.

Meshes (:func:`mesh_files`): ``NAME=PATH`` per object, one per model file (same order;
one-object models), or one models folder for all (each object's mesh by
:func:`dope_hope.io.models_dir.find_object_mesh`); their units one for all or per object
(``mesh_units``: :func:`dope_hope.geometry.value_for_object`).

New objects with no training (:func:`build_start_predictors`): a
:class:`~dope_hope.inference.mesh_start.MeshStartPredictor` per mesh, their up axes and units
one for all or per object.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dope_hope.errors import ConfigError
from dope_hope.geometry import value_for_object
from dope_hope.inference import backends  # looked up at each call: a substituted open_backend counts
from dope_hope.inference.mesh_start import MeshStartPredictor
from dope_hope.inference.options import preset_options
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.tracking import PoseTracker, class_symmetry_transforms
from dope_hope.io.models_dir import check_run_object, find_object_mesh, is_named_value, parse_mesh_args


def kept_classes(classes: Sequence[str] | None, models: list[tuple[Path, list[str]]],
                 ) -> tuple[list[list[str] | None], list[str]]:
    """Per model (path, its object names), the objects it reports, and the warnings to give.

    An object is reported by the first model, in the order given, that holds it: a later
    model holding it too skips it (one warning naming both files and the object), so that no
    object is reported twice. ``classes`` (``--classes``) keeps a subset of the objects.

    Returns:
        (kept, warnings): kept[i] is None (all of model i's objects), a subset of them, or []
        (none: the model is not run).

    Raises:
        ConfigError: a ``classes`` name no model holds (naming --classes and the models' objects).
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


def mesh_files(meshes: Sequence[str | Path], models: Sequence[Sequence[str]],
               weights: Sequence[str | Path] = ()) -> list[dict[str, Path]]:
    """``--mesh`` values -> per model, {object: mesh file} (an object left out keeps the model's
    cuboid). ``models``: each model's objects (those it reports); ``weights``: the model files,
    named in errors.

    ``meshes``: none; one models folder (every object's mesh found there); ``NAME=PATH`` values
    (each NAME an object of the run, :func:`dope_hope.io.models_dir.parse_mesh_args`, bare
    paths among them named by their files); or one bare path per model, same order (one-object
    models).

    Raises:
        ConfigError: a NAME no model reports, a bare path whose file names no object of the
        run (where the paths are not one per model), one bare path per model where a model
        reports several objects.
    """
    meshes = [Path(m) for m in meshes]
    if not meshes:
        return [{} for _ in models]
    if len(meshes) == 1 and meshes[0].is_dir():
        return [{name: find_object_mesh(name, meshes[0]) for name in names} for names in models]
    if any(is_named_value(m) for m in meshes) or len(meshes) != len(models):
        by_name = parse_mesh_args(meshes, [n for names in models for n in names])
        return [{n: by_name[n] for n in names if n in by_name} for names in models]
    out = []
    for i, (mesh, names) in enumerate(zip(meshes, models)):
        if len(names) > 1:
            model = weights[i] if i < len(weights) else f"model {i + 1}"
            raise ConfigError(f"--mesh {mesh}: {model} detects {len(names)} objects ({', '.join(names)}); "
                              "give --mesh NAME=PATH per object, or a models folder")
        out.append({names[0]: mesh} if names else {})
    return out


def run_object_values(values: str | Mapping[str, str] | None, models: Sequence[Sequence[str]], flag: str
                      ) -> str | dict[str, str] | None:
    """``flag [NAME=]VALUE`` values (one for every object, or {NAME: value}) with each NAME
    turned into the run's object it names (catalog names match case-insensitively; "" stays:
    the others); ConfigError naming ``flag NAME=VALUE`` for a NAME no model reports."""
    if not isinstance(values, Mapping):
        return values
    names = [n for group in models for n in group]
    return {(check_run_object(k, names, flag, f"{k}={v}") if k else ""): v for k, v in values.items()}


def build_predictors(weights: Sequence[Path], meshes: Sequence[str | Path] = (), *,
                     mesh_units: str | Mapping[str, str] | None = None,
                     backend: str = "auto", device: str = "cpu", threads: int | None = None,
                     options: Mapping[str, Any] | None = None, classes: Sequence[str] | None = None,
                     note: Callable[[str], None] = lambda message: None, preset: str = "fast") -> list[DopePredictor]:
    """A predictor per model file in ``weights`` that detects one of ``classes`` (all: None).

    Args:
        meshes: the ``--mesh`` values (:func:`mesh_files`), or none (the models' cuboids).
        mesh_units: one unit for every mesh file, or {NAME: unit} ("" for the others; NAME an
            object of the run). backend, device, threads: as
            :class:`~dope_hope.inference.predictor.DopePredictor` takes them.
        options: the inference options set (a mapping over the defaults,
            :class:`~dope_hope.inference.options.InferenceOptions`); without ``min_score`` each
            model's own threshold, else the default.
        note: told what each model runs as (an ONNX file: fp32 or INT8), which threshold
            a model brings along and (starting "warning: ") which model reports an object that
            several hold (:func:`kept_classes`).
        preset: the options ``options`` are read over (:func:`~dope_hope.inference.options.preset_options`;
            "fast": the packaged defaults; "accurate" with one working size for a fixed-size export).

    Raises ConfigError for meshes or units that do not fit the models, a class no model detects.
    """
    opened = [backends.open_backend(w, backend, device, threads) for w in weights]
    models = [(w, [o.class_name for o in backends.backend_objects(b)]) for w, b in zip(weights, opened)]
    kept, warnings = kept_classes(classes, models)
    for warning in warnings:
        note(f"warning: {warning}")
    reported_names = [names if keep is None else keep for (_, names), keep in zip(models, kept)]
    files = mesh_files(meshes, reported_names, weights)
    mesh_units = run_object_values(mesh_units, reported_names, "--mesh-units")
    predictors = []
    for i, (model, keep) in enumerate(zip(opened, kept)):
        if keep == []:
            continue  # none of --classes: this model is not run
        if hasattr(model, "describe"):  # ONNX: fp32 or INT8, and what INT8 costs
            note(f"model {model.describe()}")
        fixed = getattr(model, "fixed_input_hw", None) is not None
        predictors.append(DopePredictor(model, mesh=files[i] or None, mesh_units=mesh_units, classes=keep,
                                        options=preset_options(preset, options, fixed_size=fixed, meshes=bool(files[i]))))
        if predictors[-1].own_min_score:
            scores = {obj.class_name: obj.min_score for obj in predictors[-1].objects}
            text = (f"{', '.join(scores)}: min score {next(iter(scores.values())):g}"
                    if len(set(scores.values())) == 1 else
                    "min score " + ", ".join(f"{name} {score:g}" for name, score in scores.items()))
            note(f"{text}, the model's own (recorded with its weights; --min-score overrides)")
    return predictors


def stream_tracker(predictors: Sequence[DopePredictor]) -> PoseTracker:
    """The PoseTracker over ``predictors``; each class's symmetries from the mesh file its
    predictor read (``ObjectGeometry.mesh_file``, in its unit: a declaration beside it, else
    found on it), else those the model records, else the catalog category's."""
    symmetries = {obj.class_name: class_symmetry_transforms(obj.class_name, obj.mesh_file, obj.mesh_units)
                  for p in predictors for obj in p.objects if obj.mesh_file is not None}
    return PoseTracker(predictors, symmetries=symmetries)


def build_start_predictors(meshes: Mapping[str, str | Path], *, up_axes: str | Mapping[str, str] | None = None,
                           mesh_units: str | Mapping[str, str] | None = None, start: str | Path | None = None,
                           device: str = "cpu", threads: int | None = None, options: Mapping[str, Any] | None = None,
                           classes: Sequence[str] | None = None, note: Callable[[str], None] = lambda message: None,
                           preset: str = "fast") -> list[MeshStartPredictor]:
    """A :class:`~dope_hope.inference.mesh_start.MeshStartPredictor` per new object (the
    pretrained start as a detector of its mesh's cuboid, no training), in the order given;
    their network runs once per image and working size for all of them (the start's maps
    know no object). Each one's description goes to ``note``.

    Args:
        meshes: {class name: mesh file} (:func:`dope_hope.io.models_dir.new_object_meshes`).
        up_axes, mesh_units: one value for every mesh, or {NAME: value} ("" for the others;
            NAME one of ``meshes``): the vertical mesh axis (default y) and the file's unit.
        start, device, threads, options: as :class:`MeshStartPredictor` takes them.
        classes: keep these of ``meshes`` (``--classes``; None: all).
        preset: the options ``options`` are read over (:func:`~dope_hope.inference.options.preset_options`
            for a new object: the "accurate" preset's ICP, not its sizes or turns).

    Raises ConfigError for a NAME of ``up_axes``, ``mesh_units`` or ``classes`` that is not one
    of ``meshes``.
    """
    names = [list(meshes)]
    up_axes = run_object_values(up_axes, names, "--up-axis")
    mesh_units = run_object_values(mesh_units, names, "--mesh-units")
    kept = None if classes is None else {check_run_object(c, names[0], "--classes", c) for c in classes}
    predictors = []
    for name, path in meshes.items():
        if kept is not None and name not in kept:
            continue
        p = MeshStartPredictor(path, class_name=name, up_axis=value_for_object(up_axes, name) or "y", mesh_units=mesh_units,
                               start=start, device=device, threads=threads,
                               options=preset_options(preset, options, new_object=True))
        note(p.describe())
        predictors.append(p)
    return predictors
