"""Which models a run of ``dope-hope infer`` or of the ROS 2 node runs, and their predictors:
trained model files (a :class:`~dope_hope.inference.predictor.DopePredictor` each,
:func:`~dope_hope.inference.model_set.build_predictors`), or the pretrained start as the
detector of each new object's mesh when meshes come without weights
(:func:`~dope_hope.inference.model_set.build_start_predictors`). Both front ends build their
predictors here, so the same options give the same poses.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dope_hope.demo_object import DEMO_CLASS_NAME
from dope_hope.errors import ConfigError
from dope_hope.inference.model_set import build_predictors, build_start_predictors
from dope_hope.io.models_dir import new_object_meshes


@dataclass(frozen=True)
class ModelChoice:
    """The models of a run, as ``infer``'s options name them.

    weights: model files (.pt / .onnx); empty: ``default_weights`` of :func:`build_run_predictors`.
    meshes: ``[NAME=]PATH`` values or one models folder (``--mesh``). mesh_units, up_axes: one
    value for every object or {NAME: value} (:func:`~dope_hope.io.models_dir.named_object_values`). start: the pretrained
    start of new objects (None: the shipped one). classes: the objects reported (None: all).
    backend, device, threads: as :class:`~dope_hope.inference.predictor.DopePredictor` takes them.
    """

    weights: tuple[Path, ...] = ()
    meshes: tuple[Path, ...] = ()
    mesh_units: str | Mapping[str, str] | None = None
    up_axes: str | Mapping[str, str] | None = None
    start: Path | None = None
    classes: tuple[str, ...] | None = None
    backend: str = "auto"
    device: str = "cpu"
    threads: int | None = None


def new_objects(choice: ModelChoice, default_weights: Path | None) -> dict[str, Path] | None:
    """{class name: mesh file} of the new objects the pretrained start detects (no weights,
    every mesh a [NAME=]FILE or one models folder, unless they are the default model's demo
    object alone), else None.

    Raises:
        ConfigError: ``--up-axis`` / ``--start`` without new objects.
    """
    meshes = list(choice.meshes)
    new = not choice.weights and meshes
    found = new_object_meshes(meshes) if new else None
    demo = (found is not None and [n.lower() for n in found] == [DEMO_CLASS_NAME.lower()]
            and default_weights is not None)
    if found is not None and not demo:
        return found
    flags = [f for f, v in (("--up-axis", choice.up_axes), ("--start", choice.start)) if v]
    if flags and choice.weights:
        raise ConfigError(f"{', '.join(flags)}: for new objects detected by the pretrained start "
                          "(--mesh FILE, no --weights); a trained model knows its objects")
    if flags:
        raise ConfigError(f"{', '.join(flags)}: give the new objects' mesh files (--mesh FILE) and no --weights")
    return None


def build_run_predictors(choice: ModelChoice, options: Mapping[str, Any] | None, default_weights: Path | None,
                         note: Callable[[str], None] = lambda message: None, preset: str = "fast") -> list:
    """The predictors of ``choice``: the pretrained start's for new objects' meshes
    (:func:`new_objects`), else one per model file (``default_weights`` when none is given).

    Args:
        options: the inference options set (a mapping over the defaults,
            :class:`~dope_hope.inference.options.InferenceOptions`).
        default_weights: the model run when ``choice`` names none (the shipped demo model), or None.
        note: told what each model runs as and which threshold it brings.
        preset: the inference preset under ``options`` ("fast": the packaged defaults, what a
            stream and the ROS node run; "accurate": still images;
            :data:`~dope_hope.inference.options.PRESETS`).

    Raises:
        ConfigError: no weights and no default; meshes, units or classes that do not fit.
    """
    meshes = new_objects(choice, default_weights)
    classes = None if choice.classes is None else list(choice.classes)
    if meshes is not None:
        return build_start_predictors(meshes, up_axes=choice.up_axes, mesh_units=choice.mesh_units, start=choice.start,
                                      device=choice.device, threads=choice.threads, options=options,
                                      classes=classes, note=note, preset=preset)
    weights = list(choice.weights) or ([default_weights] if default_weights is not None else [])
    if not weights:
        raise ConfigError("--weights is required (no demo model at dope_hope/assets/demo_lite.pt "
                          "in this installation)")
    return build_predictors(weights, list(choice.meshes), mesh_units=choice.mesh_units, backend=choice.backend,
                            device=choice.device, threads=choice.threads, options=options, classes=classes,
                            note=note, preset=preset)
