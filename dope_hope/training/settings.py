"""Training settings: the job, the sections of a training recipe (:class:`TrainConfig`: their
defaults and checks), the object's info."""
from __future__ import annotations

import dataclasses
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.assets import DEMO_WEIGHTS, PRETRAINED_WEIGHTS
from dope_hope.catalog import CATEGORIES, get_object
from dope_hope.config import (
    SectionSettings,
    at_least,
    boolean,
    fraction,
    merge,
    nonnegative_float,
    one_of,
    or_none,
    positive_float,
    section,
)
from dope_hope.errors import ConfigError, DopeHopeError, InputFileError, UnknownObjectError
from dope_hope.geometry import fit_cuboid
from dope_hope.io.bop_scenes import recorded_box_size
from dope_hope.io.dope_json import read_dope_json, recorded_cuboid_size
from dope_hope.io.models_dir import find_object_mesh, is_named_value, parse_mesh_args
from dope_hope.io.paths import require_file
from dope_hope.model.settings import InputSettings, ModelSettings
from dope_hope.training.augment import AugmentParams

#: ``--init`` choices besides a checkpoint path.
INIT_CHOICES = ("auto", "pretrained", "demo", "none")

# =============================================================================== job + config
@dataclass
class TrainJob:
    """What one ``dope-hope train`` call asks for (the config holds the recipe).

    Attributes:
        data: training folders (DOPE format, or BOP datasets: :mod:`dope_hope.training.sources`).
        object_name: class to train (case-insensitive match against the annotations); the
            first of ``objects`` in a run of several.
        out: output folder (checkpoints, metrics.csv / metrics.jsonl, summary.json).
        val: validation folders, or empty for a seeded split of ``data``.
        resume: checkpoint to continue from, or None.
        mesh: optional mesh whose AABB gives the cuboid size recorded in the checkpoint.
        symmetries: optional symmetry declaration file (else ``model_info.json`` beside the
            mesh is used when present; :mod:`dope_hope.symmetry.resolve`).
        backbone_weights: optional local VGG19 state dict (arch dope).
        init_weights: optional dope-hope checkpoint whose network weights start this run
            (fine-tuning: fresh optimizer, schedule and step count; same architecture).
        init_reason: what the run starts from, in words (logged; from :func:`resolve_init`).
        device: "auto" (CUDA when available), "cpu" or "cuda[:i]".
        progress: show tqdm bars (rank 0).
        overrides: nested recipe values (a resumed run's ``--epochs``, ``--set``...): merged
            over the given recipe, or over the checkpoint's when resuming (:func:`run_recipe`,
            the one merge; a new run's command gives its recipe whole and leaves this empty).
        on_step: hook called with (trainer, step) after every optimizer step (tests use it to
            interrupt a run at a given step); typed loosely, as this module sits below the trainer.
        clock: the seconds the time budget counts (default ``time.monotonic``; tests inject a
            clock to make the plans of a time-limited run reproducible).
        started: the clock's reading when the budget started (the command's start), or None
            for the trainer's start.
        objects: the classes of a run of several objects, in channel-group order (empty: the
            one class ``object_name``); see :attr:`class_names`.
        meshes: {class: mesh file} of the objects (several; one object: ``mesh``).
        units: {class: unit of its mesh file} ("m", "cm", "mm"; default the suffix's).
        mesh_name: the NAME of ``--mesh NAME=PATH`` on a resumed run without ``--object``
            (checked against the run's objects: ``training.resume.check_resume_flags``), or None.
    """

    data: list[Path]
    object_name: str
    out: Path
    val: list[Path] = field(default_factory=list)
    resume: Path | None = None
    mesh: Path | None = None
    symmetries: Path | None = None
    backbone_weights: Path | None = None
    init_weights: Path | None = None
    init_reason: str = ""
    device: str = "auto"
    progress: bool = True
    overrides: dict[str, Any] = field(default_factory=dict)
    on_step: Callable[[Any, int], None] | None = None
    clock: Callable[[], float] | None = None
    started: float | None = None
    objects: list[str] = field(default_factory=list)
    meshes: dict[str, Path] = field(default_factory=dict)
    units: dict[str, str] = field(default_factory=dict)
    mesh_name: str | None = None

    @property
    def class_names(self) -> list[str]:
        """The run's classes in channel-group order (one: ``[object_name]``)."""
        return list(self.objects) if self.objects else [self.object_name]

    def unit_of(self, name: str) -> str | None:
        """The unit of class ``name``'s mesh file (None: its suffix's default)."""
        return self.units.get(name, self.units.get("") if len(self.class_names) == 1 else None)

    def mesh_of(self, name: str) -> Path | None:
        """The mesh file of class ``name`` (``meshes``, else ``mesh`` for a one-object run)."""
        if name in self.meshes:
            return self.meshes[name]
        return self.mesh if len(self.class_names) == 1 else None


#: The longest time budget accepted, minutes (a year): longer ones are mistakes (1e308
#: minutes is no number of seconds a clock can count); leave the budget out for no limit.
MAX_TIME_LIMIT_MIN = 525_600.0


def check_time_limit(value: Any, name: str = "train.time_limit_min") -> float:
    """A time budget in minutes: a finite number > 0 and at most :data:`MAX_TIME_LIMIT_MIN`;
    ConfigError naming ``name`` otherwise."""
    minutes = positive_float(value, name)
    if minutes > MAX_TIME_LIMIT_MIN:
        raise ConfigError(f"{name} must be at most {MAX_TIME_LIMIT_MIN:g} minutes (a year; leave it out for "
                          f"no time limit), got {value!r}")
    return minutes


def _below_one(value: Any, name: str) -> float:
    """A fraction in [0, 1)."""
    if nonnegative_float(value, name) >= 1:
        raise ConfigError(f"{name} must be a fraction in [0, 1), got {value!r}")
    return float(value)


def _betas(value: Any, name: str) -> list[float]:
    if (not isinstance(value, (list, tuple)) or len(value) != 2
            or not all(0 <= nonnegative_float(b, name) < 1 for b in value)):
        raise ConfigError(f"{name} must be two numbers in [0, 1), got {value!r}")
    return list(value)


@dataclass(frozen=True)
class TrainSettings(SectionSettings):
    """The ``train`` section of a training recipe: the optimization and the run.

    batch_size: images per step and process. epochs / steps (null: from the epochs) /
    time_limit_min (minutes, null: none): the run ends at the first reached. optimizer (adam,
    adamw), lr, weight_decay, betas. schedule: constant | cosine | step | wsd, with warmup_steps,
    min_lr_factor (the cosine's and wsd's floor), decay_share (wsd: the last share of the planned
    steps after the warm-up over which the rate falls linearly to its floor), cosine_replan (restart | continue: how the cosine goes on when
    a time budget re-plans the run's end, :mod:`dope_hope.training.schedule`), step_epochs /
    step_gamma (step). grad_clip: max global grad
    norm or null. loss: mse; belief_weight, affinity_weight; foreground_weight: belief cells
    weigh 1 + w * target. workers: DataLoader processes; threads: torch threads (null: torch's
    default); frame_cache_mb: memory (MiB) for decoded frames kept across epochs, shared with
    the workers (0: decode every time). checkpoint_every (epochs) / checkpoint_every_steps (0: off). amp: bf16 autocast
    where native; channels_last: NHWC tensors. seed. val_fraction (the split of --data
    without --val), val_every (epochs, 0: off), val_radius_px, val_peak_threshold,
    val_batch_size (null: batch_size). max_instances per frame; min_visibility of an instance;
    include_empty_frames. log_every (steps). horizon_estimate_after: steps before a time
    budget becomes a step count. plots: results.png + val_snapshot.png after each validation.
    calibrate_thresholds: at the run's end, each object's score threshold chosen on the
    validation frames and recorded in best.pt (:mod:`dope_hope.training.calibration`).
    """

    SECTION = "train"
    RULES = {
        "batch_size": at_least(1), "epochs": at_least(1), "steps": or_none(at_least(1)),
        "time_limit_min": or_none(check_time_limit), "optimizer": one_of("adam", "adamw"),
        "lr": nonnegative_float, "weight_decay": nonnegative_float, "betas": _betas,
        "schedule": one_of("constant", "cosine", "step", "wsd"), "warmup_steps": at_least(0),
        "min_lr_factor": nonnegative_float, "decay_share": fraction, "cosine_replan": one_of("restart", "continue"),
        "step_epochs": at_least(1), "step_gamma": positive_float,
        "grad_clip": or_none(positive_float), "loss": one_of("mse"), "belief_weight": nonnegative_float,
        "affinity_weight": nonnegative_float, "foreground_weight": nonnegative_float,
        "workers": at_least(0), "threads": or_none(at_least(1)), "frame_cache_mb": nonnegative_float,
        "checkpoint_every": at_least(0),
        "checkpoint_every_steps": or_none(at_least(0)), "amp": boolean, "channels_last": boolean,
        "seed": at_least(0), "val_fraction": _below_one, "val_every": at_least(0),
        "val_radius_px": positive_float, "val_peak_threshold": nonnegative_float,
        "val_batch_size": or_none(at_least(1)), "max_instances": at_least(1),
        "min_visibility": nonnegative_float, "include_empty_frames": boolean, "log_every": at_least(1),
        "horizon_estimate_after": at_least(2), "plots": boolean, "calibrate_thresholds": boolean,
    }

    batch_size: int = 16
    epochs: int = 30
    steps: int | None = None
    time_limit_min: float | None = None
    optimizer: str = "adam"
    lr: float = 1e-4
    weight_decay: float = 0.0
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    schedule: str = "constant"
    warmup_steps: int = 0
    min_lr_factor: float = 0.01
    decay_share: float = 0.2
    cosine_replan: str = "restart"
    step_epochs: int = 20
    step_gamma: float = 0.1
    grad_clip: float | None = None
    loss: str = "mse"
    belief_weight: float = 1.0
    affinity_weight: float = 1.0
    foreground_weight: float = 0.0
    workers: int = 2
    threads: int | None = None
    frame_cache_mb: float = 2048.0
    checkpoint_every: int = 1
    checkpoint_every_steps: int | None = 0
    amp: bool = True
    channels_last: bool = True
    seed: int = 0
    val_fraction: float = 0.1
    val_every: int = 1
    val_radius_px: float = 5.0
    val_peak_threshold: float = 0.1
    val_batch_size: int | None = None
    max_instances: int = 8
    min_visibility: float = 0.0
    include_empty_frames: bool = True
    log_every: int = 20
    horizon_estimate_after: int = 20
    plots: bool = True
    calibrate_thresholds: bool = True


def _symmetry(value: Any, name: str) -> Any:
    if value in (None, False) or (isinstance(value, str) and value.lower() in ("none", "auto", *CATEGORIES)):
        return value
    raise ConfigError(f"{name} must be none, auto or one of {', '.join(CATEGORIES)}, got {value!r}")


@dataclass(frozen=True)
class TargetsSettings(SectionSettings):
    """The ``targets`` section: sigma of the belief maps' Gaussian blobs and radius of the
    affinity disks, map pixels; symmetry: none (official labels), auto, or a category
    (cuboid, bottle, cylinder): symmetry-aware relabelling of symmetric views
    (:mod:`dope_hope.symmetry.labels`)."""

    SECTION = "targets"
    RULES = {"sigma": positive_float, "radius": positive_float, "symmetry": _symmetry}

    sigma: float = 2.0
    radius: float = 1.0
    symmetry: str | None = "none"


@dataclass(frozen=True)
class TrainConfig(SectionSettings):
    """A training recipe (``configs/lite.yaml``, ``dope_dr_50.yaml``, ...): its sections, each
    over its defaults. A recipe file holds only what differs from them."""

    SECTION = ""

    model: ModelSettings = section(ModelSettings)
    input: InputSettings = section(InputSettings)
    targets: TargetsSettings = section(TargetsSettings)
    train: TrainSettings = section(TrainSettings)
    augment: AugmentParams = section(AugmentParams)


def run_recipe(config: TrainConfig | Mapping[str, Any] | None, overrides: Mapping[str, Any] | None = None,
               recorded: Mapping[str, Any] | None = None) -> TrainConfig:
    """The recipe a run trains with, checked once: ``recorded`` (a resumed run's checkpoint's
    recipe) or else ``config`` (settings, or a recipe mapping over the defaults), with
    ``overrides`` (nested values, e.g. the command line's) deep-merged over it.

    Raises:
        ConfigError: an unknown section or key, or a bad value, naming ``section.key``.
    """
    base = recorded if recorded is not None else config
    if isinstance(base, TrainConfig) and not overrides:
        return base
    values = base.to_dict() if isinstance(base, TrainConfig) else dict(base or {})
    return TrainConfig.from_mapping(merge(values, dict(overrides or {})))


def with_train_values(recipe: TrainConfig, **values: Any) -> TrainConfig:
    """``recipe`` with the ``train`` keys ``values`` set (each checked by its rule; ConfigError
    naming ``train.key``)."""
    return dataclasses.replace(recipe, train=dataclasses.replace(recipe.train, **values))


#: An annotation's projected cuboid implies its box when the fitted box reprojects within
#: this many pixels (RMS) of it (else its pose is in another frame: no size is read from it).
FIT_RMS_PX = 2.0


def annotated_size(name: str, records: Sequence[Any], object_index: int = 0) -> tuple[np.ndarray, str] | None:
    """(size (3,) m, where from) of ``name``'s box as the data says, or None: the size the
    dataset records (a synth frame's JSON, an NDDS settings file, a BOP dataset's
    models_info.json), else the one box the instances' projected cuboids imply with their
    poses (:func:`dope_hope.geometry.fit_cuboid`; None when they do not fit one box within
    :data:`FIT_RMS_PX`, e.g. poses in another frame). Looks at the first five records holding
    object ``object_index``."""
    holding = [r for r in records if np.any(r.object_indices() == object_index)][:5]
    recorded = _recorded_size(name, holding)
    if recorded is not None:
        return recorded[0], f"the size {recorded[1].name} records"
    views = []
    for r in holding:
        if r.json_path.name == "scene_gt.json":
            continue
        try:
            frame = read_dope_json(r.json_path)
        except (DopeHopeError, ValueError, KeyError, TypeError, OSError):
            continue
        views += [(obj.projected_cuboid, frame.K, obj.R, obj.t) for obj in frame.objects
                  if obj.class_name.lower() == name.lower() and obj.projected_cuboid is not None]
    fitted = fit_cuboid(views)
    if fitted is None or fitted[2] > FIT_RMS_PX:
        return None
    return fitted[0], (f"the box the annotated projected cuboids imply ({len(views)} instances, e.g. in "
                       f"{holding[0].json_path.name})")


def _recorded_size(name: str, records: Sequence[Any]) -> tuple[np.ndarray, Path] | None:
    """(size (3,) m, the annotation file) of the first of ``records`` whose dataset records
    ``name``'s box, or None."""
    for r in records:
        if r.json_path.name == "scene_gt.json":
            size = recorded_box_size(r.json_path, name)
        else:
            size = recorded_cuboid_size(r.json_path, name)
        if size is not None:
            return size, r.json_path
    return None


def object_info(name: str, records: Sequence[Any], mesh: Path | None, units: str | None = None,
                object_index: int = 0) -> tuple[dict[str, Any], str]:
    """Checkpoint ``object`` entry (class_name, size_m in the mesh frame, frame "mesh") and
    where the size came from: a mesh's AABB (file in ``units``, default its suffix's) > the
    size the dataset records (a synth frame's JSON, an NDDS settings file, a BOP dataset's
    models_info.json) > the catalog. ``object_index``: the object's index in the records'
    ``classes``.

    Raises:
        ConfigError: a mesh whose box does not match the box the data says
        (:func:`annotated_size`, extents in any order, within
        :data:`dope_hope.io.meshes.MESH_SIZE_TOLERANCE`): every pose the model gives would
        be off by the ratio.
    """
    from dope_hope.model.checkpoint import make_object_info  # noqa: PLC0415 (torch and trimesh only for the checkpoint's object entry)

    try:
        hope = get_object(name)
        name = hope.name
    except UnknownObjectError:
        hope = None
    if mesh is not None:
        from dope_hope.io.meshes import check_mesh_box, load_mesh, mesh_cuboid  # noqa: PLC0415 (trimesh only for a run given a mesh)

        loaded = load_mesh(mesh, units=units)
        size, _ = mesh_cuboid(loaded)
        implied = annotated_size(name, records, object_index)
        if implied is not None:
            check_mesh_box(size, implied[0], f"--mesh {mesh}", name, implied[1], any_axis_order=True,
                           units=loaded.metadata["source_units"])
        return make_object_info(name, size, "mesh"), f"mesh {Path(mesh).name}"
    recorded = _recorded_size(name, [r for r in records if np.any(r.object_indices() == object_index)][:5])
    if recorded is not None:
        return make_object_info(name, recorded[0], "mesh"), f"dataset {recorded[1].name}"
    if hope is None:
        raise ConfigError(f"cannot tell the cuboid size of {name!r}: the dataset records none and it is "
                          "not a HOPE object; pass --mesh")
    return make_object_info(name, hope.size_array, "mesh"), "catalog"


def resolve_init(choice: str | None, recipe: TrainConfig) -> tuple[Path | None, str]:
    """The checkpoint whose weights start a new run (``--init``) and a line saying why.

    Args:
        choice: None or "auto" (the shipped pretrained start when the run's ``model`` section
            and input normalization are the ones it was trained with, else a random start),
            "pretrained", "demo" (the shipped demo model), "none" (random start) or a path.
        recipe: the run's recipe.

    Raises:
        InputFileError: "pretrained" / "demo" where this installation does not ship the file.
        ModelFileError: "pretrained" for another architecture (its shapes differ).
    """
    value = "auto" if choice is None else str(choice)
    if value == "none":
        return None, "random start (--init none)"
    if value == "demo":
        if not DEMO_WEIGHTS.is_file():
            raise InputFileError(DEMO_WEIGHTS, "--init demo: this installation has no shipped demo model")
        return DEMO_WEIGHTS, "the shipped demo model (--init demo)"
    if value in ("auto", "pretrained"):
        if not PRETRAINED_WEIGHTS.is_file():
            if value == "pretrained":
                raise InputFileError(PRETRAINED_WEIGHTS, "--init pretrained: this installation ships no "
                                                         "pretrained start")
            return None, "random start (this installation ships no pretrained start)"
        if value == "pretrained" or same_architecture(recipe, PRETRAINED_WEIGHTS):
            return PRETRAINED_WEIGHTS, f"the shipped pretrained start {PRETRAINED_WEIGHTS.name}"
        return None, ("random start: the config's model differs from the shipped pretrained lite "
                      "start's (--init none to say so, --init PATH for another checkpoint)")
    return Path(value), f"the weights of {value} (--init)"


def resolve_resume(choice: str | None, out: Path, init: str | None) -> tuple[Path | None, str | None]:
    """The checkpoint a run continues from (``--resume``) and the ``--init`` that still applies.

    Args:
        choice: None (a new run), "auto" (``out/last.pt`` when it exists, else a new run) or a
            checkpoint path.
        out: the run's output folder.
        init: the ``--init`` given, or None.

    Returns:
        (checkpoint or None, init or None): "auto" finding ``last.pt`` continues it with its
        own weights (a given ``--init`` is ignored, said in a warning).

    Raises:
        ConfigError: a checkpoint path together with ``--init``.
        InputFileError: a checkpoint path that is not a readable file.
    """
    log = logging.getLogger(__name__)
    if choice is None:
        return None, init
    if choice != "auto":
        if init is not None:
            raise ConfigError("--resume PATH continues a run with its own weights; --init starts a new run "
                              "from other weights: give one of them")
        return require_file(Path(choice), "checkpoint to resume from"), None
    candidate = Path(out) / "last.pt"
    if not candidate.is_file():
        log.info("--resume: %s does not exist yet, starting fresh", candidate)
        return None, init
    if init is not None:
        log.warning("--init %s ignored: --resume continues %s with its own weights", init, candidate)
    return candidate, None


def same_architecture(recipe: TrainConfig, checkpoint: Path) -> bool:
    """True when ``recipe`` builds the network ``checkpoint`` holds (same ``model`` section and
    input normalization), up to ``model.num_objects``: a one-object start is widened to the
    run's objects (:func:`dope_hope.model.network.widen_to_objects`)."""
    from dope_hope.model.checkpoint import load_checkpoint  # noqa: PLC0415 (torch only to read the checkpoint)

    saved = load_checkpoint(checkpoint)["config"]
    saved_model = ModelSettings.from_mapping(saved.get("model"))
    saved_norm = InputSettings.from_mapping(saved.get("input")).normalization
    # a one-object start widens to any number of objects
    return (dataclasses.replace(saved_model, num_objects=1) == dataclasses.replace(recipe.model, num_objects=1)
            and saved_norm == recipe.input.normalization)


def train_meshes(objects: Sequence[str], mesh_args: Sequence[str] | None, models_dir: Path | None,
                 units: Sequence[str] | None = None) -> tuple[dict[str, Path], dict[str, str]]:
    """The objects' mesh files and their units (``train --mesh / --models-dir / --units``):
    ({class: mesh}, {class: unit}).

    ``--mesh`` values pair with the objects in order when there is one per object (else
    ``NAME=PATH`` or a file that names its object; a NAME that is not an object of the run is
    refused: :func:`dope_hope.io.models_dir.parse_mesh_args`);
    ``--models-dir`` is searched for every object (:func:`~dope_hope.io.models_dir.find_object_mesh`).
    Without objects (a resumed run) one mesh is the run's object's, keyed by the NAME of
    ``NAME=PATH`` (checked on resume) or "".

    Raises:
        ConfigError: both --mesh and --models-dir; a mesh of no object of the run; units not
            one or one per mesh.
    """
    names = list(objects)
    if mesh_args and models_dir is not None:
        raise ConfigError("give either --mesh or --models-dir, not both")
    meshes: dict[str, Path] = {}
    if models_dir is not None:
        meshes = {n: find_object_mesh(n, models_dir) for n in names}
    elif mesh_args and not names:  # a resumed run's one object, named by its checkpoint
        if len(mesh_args) != 1:
            raise ConfigError(f"--mesh: {len(mesh_args)} meshes for a resumed run; name its objects with --object")
        text = str(mesh_args[0])
        name, path = text.split("=", 1) if is_named_value(text) else ("", text)
        meshes = {name: Path(path)}
    elif mesh_args:
        meshes = parse_mesh_args(mesh_args, names, in_order=True)
    if not units:
        return meshes, {}
    if not meshes:
        raise ConfigError("--units: no --mesh / --models-dir to apply them to")
    if len(units) not in (1, len(meshes)):
        raise ConfigError(f"--units: {len(units)} values for {len(meshes)} meshes; give one, or one per mesh")
    unit_list = list(units) * len(meshes) if len(units) == 1 else list(units)
    return meshes, dict(zip(meshes, unit_list))
