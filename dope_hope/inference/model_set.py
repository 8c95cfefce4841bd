"""The models of one `dope-hope infer` run: a :class:`~dope_hope.inference.predictor.DopePredictor`
per model file (its objects, its meshes, the classes it reports) and, on a stream, the
:class:`~dope_hope.inference.tracking.PoseTracker` over them.

An object that several model files hold is reported by the first of them only
(:func:`kept_classes`), never twice.

Meshes: one per model file (same order; one-object models), or one models folder for all
(each object's mesh by :func:`dope_hope.io.models_dir.find_object_mesh`).
"""
from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from dope_hope.errors import ConfigError
from dope_hope.inference import backends  # looked up at each call: a substituted open_backend counts
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.tracking import PoseTracker, object_symmetries
from dope_hope.io.models_dir import find_object_mesh


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


def build_predictors(weights: Sequence[Path], meshes: Sequence[Path] = (), *, mesh_units: str | None = None,
                     backend: str = "auto", device: str = "cpu", threads: int | None = None,
                     options: Mapping[str, Any] | None = None, classes: Sequence[str] | None = None,
                     note: Callable[[str], None] = lambda message: None) -> list[DopePredictor]:
    """A predictor per model file in ``weights`` that detects one of ``classes`` (all: None).

    Args:
        meshes: one mesh per model file (one-object models), or one models folder, or none
            (the models' cuboids).
        mesh_units, backend, device, threads: as
            :class:`~dope_hope.inference.predictor.DopePredictor` takes them.
        options: the inference options set (a mapping over the defaults,
            :class:`~dope_hope.inference.options.InferenceOptions`); without ``min_score`` each
            model's own threshold, else the default.
        note: told what each model runs as (an ONNX file: fp32 or INT8), which threshold
            a model brings along and (starting "warning: ") which model reports an object that
            several hold (:func:`kept_classes`).

    Raises ConfigError for meshes that do not fit the models, a class no model detects.
    """
    meshes = list(meshes)
    mesh_dir = None
    if len(meshes) == 1 and meshes[0].is_dir():
        mesh_dir = meshes[0]
    elif meshes and len(meshes) != len(weights):
        raise ConfigError(f"give one --mesh per --weights ({len(weights)}), or one mesh folder; "
                          f"got {len(meshes)} meshes")
    opened = [backends.open_backend(w, backend, device, threads) for w in weights]
    models = [(w, [o.class_name for o in backends.backend_objects(b)]) for w, b in zip(weights, opened)]
    kept, warnings = kept_classes(classes, models)
    for warning in warnings:
        note(f"warning: {warning}")
    predictors = []
    for i, (model, (w, names), keep) in enumerate(zip(opened, models, kept)):
        if keep == []:
            continue  # none of --classes: this model is not run
        if hasattr(model, "describe"):  # ONNX: fp32 or INT8, and what INT8 costs
            note(f"model {model.describe()}")
        reported = names if keep is None else keep
        mesh = None
        if mesh_dir is not None:
            mesh = {name: find_object_mesh(name, mesh_dir) for name in reported}
        elif meshes:
            if len(reported) > 1:
                raise ConfigError(f"--mesh {meshes[i]}: {w} detects {len(reported)} objects "
                                  f"({', '.join(reported)}); give a models folder as --mesh")
            mesh = meshes[i]
        predictors.append(DopePredictor(model, mesh=mesh, mesh_units=mesh_units, classes=keep,
                                        options=dict(options or {})))
        if "min_score" not in (options or {}) and backends.model_min_score(model) is not None:
            note(f"{', '.join(reported)}: min score {predictors[-1].options.min_score:g}, "
                 "the model's own (recorded with its weights; --min-score overrides)")
    return predictors


def stream_tracker(predictors: Sequence[DopePredictor], meshes: Sequence[Path] = (),
                   mesh_units: str | None = None) -> PoseTracker:
    """The PoseTracker over ``predictors``; each class's symmetries from its mesh (``meshes`` as
    :func:`build_predictors` takes them: a declaration beside it, else found on it), else those
    the model records, else the catalog category's."""
    meshes = list(meshes)
    symmetries = {}
    for i, p in enumerate(predictors):
        for name in p.class_names:
            path = None
            if len(meshes) == 1 and meshes[0].is_dir():
                path = find_object_mesh(name, meshes[0])
            elif meshes and len(p.class_names) == 1:
                path = meshes[i]
            if path is not None:  # else the model's recorded symmetries, else the catalog's
                symmetries[name] = object_symmetries(name, path, mesh_units)
    return PoseTracker(predictors, symmetries=symmetries)
