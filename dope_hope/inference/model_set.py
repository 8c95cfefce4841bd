"""The models of one `dope-hope infer` run: a :class:`~dope_hope.inference.predictor.DopePredictor`
per model file (its objects, its meshes, the classes it reports) and, on a stream, the
:class:`~dope_hope.inference.tracking.PoseTracker` over them.

Meshes: one per model file (same order; one-object models), or one models folder for all
(each object's mesh by :func:`dope_hope.io.models_dir.find_object_mesh`).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from dope_hope.errors import ConfigError
from dope_hope.inference import backends  # looked up at each call: a substituted open_backend counts
from dope_hope.inference.predictor import DopePredictor
from dope_hope.inference.tracking import PoseTracker, object_symmetries
from dope_hope.io.models_dir import find_object_mesh


def kept_classes(classes: Sequence[str] | None, models: list[tuple[Path, list[str]]]) -> list[list[str] | None]:
    """Per model (path, its object names), the ``classes`` it detects (None: all its objects;
    []: none, not run). ConfigError naming --classes and the models' objects for a class no
    model detects."""
    if not classes:
        return [None] * len(models)
    known = [n for _, names in models for n in names]
    for c in classes:
        if c.lower() not in {n.lower() for n in known}:
            raise ConfigError(f"--classes: {c!r} is not an object of the model(s) (known: {', '.join(known)})")
    wanted = {c.lower() for c in classes}
    return [[n for n in names if n.lower() in wanted] for _, names in models]


def build_predictors(weights: Sequence[Path], meshes: Sequence[Path] = (), *, mesh_units: str | None = None,
                     backend: str = "auto", device: str = "cpu", threads: int | None = None,
                     height: int | None = None, min_score: float | None = None, pose_search: str = "hypotheses",
                     icp: bool = False, classes: Sequence[str] | None = None,
                     note: Callable[[str], None] = lambda message: None) -> list[DopePredictor]:
    """A predictor per model file in ``weights`` that detects one of ``classes`` (all: None).

    Args:
        meshes: one mesh per model file (one-object models), or one models folder, or none
            (the models' cuboids).
        mesh_units, backend, device, threads, height, pose_search, icp: as
            :class:`~dope_hope.inference.predictor.DopePredictor` takes them.
        min_score: the score threshold of every model (None: each model's own, else the
            inference options').
        note: told what each model runs as (an ONNX file: fp32 or INT8) and which threshold
            a model brings along.

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
    kept = kept_classes(classes, models)
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
        given = {} if min_score is None else {"min_score": min_score}
        predictors.append(DopePredictor(model, height=height, mesh=mesh, mesh_units=mesh_units,
                                        pose_search=pose_search, icp=icp, classes=keep, **given))
        if min_score is None and backends.model_min_score(model) is not None:
            note(f"{', '.join(reported)}: min score {predictors[-1].options.min_score:g}, "
                 "the model's own (recorded with its weights; --min-score overrides)")
    return predictors


def stream_tracker(predictors: Sequence[DopePredictor], meshes: Sequence[Path] = (),
                   mesh_units: str | None = None) -> PoseTracker:
    """The PoseTracker over ``predictors``; each class's symmetries from the declaration beside
    its mesh (``meshes`` as :func:`build_predictors` takes them)."""
    meshes = list(meshes)
    symmetries = {}
    for i, p in enumerate(predictors):
        for name in p.class_names:
            path = None
            if len(meshes) == 1 and meshes[0].is_dir():
                path = find_object_mesh(name, meshes[0])
            elif meshes and len(p.class_names) == 1:
                path = meshes[i]
            symmetries[name] = object_symmetries(name, path, mesh_units)
    return PoseTracker(predictors, symmetries=symmetries)
