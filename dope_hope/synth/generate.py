"""Frame generation in memory: :class:`FrameGenerator` (one renderer, frame after frame),
:func:`render_frame` (one frame), and :class:`SynthJob` (what a dataset's frames are made of).
A dataset on disk is :func:`dope_hope.synth.to_disk.generate_dataset`.

Frame ``i`` of a dataset with seed ``S`` depends only on (S, i), the inputs and the config:
its random streams come from ``np.random.SeedSequence([S, i])`` (see scene.frame_streams).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dope_hope.annotation import FrameAnnotation
from dope_hope.config import SectionSettings
from dope_hope.errors import ConfigError
from dope_hope.synth.annotate import InstanceStats, TargetBox, annotate_frame, canonical_pose_labels
from dope_hope.synth.assets import (
    DistractorLibrary,
    MeshAsset,
    guess_class_name,
    list_distractor_meshes,
)
from dope_hope.synth.background import BackgroundSource
from dope_hope.synth.depth_noise import add_realsense_noise, noise_kwargs
from dope_hope.synth.hard_negatives import TargetLook
from dope_hope.synth.postprocess import composite, post_process
from dope_hope.synth.scene import SceneSpec, frame_streams, sample_scene
from dope_hope.synth.settings import load_synth_config, parse_size
from dope_hope.synth.writer import write_frame
from dope_hope.version import __version__

GENERATOR_NAME = "dope-hope synth"


@dataclass
class SynthFrame:
    """One generated frame in memory.

    Attributes:
        index: frame index; rgb: (H, W, 3) uint8; depth: (H, W) float32 metres as written
            (with RealSense noise when enabled, 0 = no measurement); depth_clean: (H, W)
            float32 metres, exact; seg: (H, W) uint8 ids (0 background, 1..k targets,
            seg_distractor_base + j distractors); annotation: targets' FrameAnnotation;
            stats: per-target pixel counts; scene: the sampled scene; alone_depth: seg id ->
            (H, W) depth of that target rendered alone (only when requested); target: the
            frame's (first) target asset; category: its HOPE category (procedural objects
            only); targets: every target object's asset (``ObjectSpec.target_index`` order).
    """

    index: int
    rgb: np.ndarray
    depth: np.ndarray
    depth_clean: np.ndarray
    seg: np.ndarray
    annotation: FrameAnnotation
    stats: list[InstanceStats]
    scene: SceneSpec
    target: MeshAsset
    alone_depth: dict[int, np.ndarray] = field(default_factory=dict)
    category: str | None = None
    targets: list[MeshAsset] = field(default_factory=list)

    def json_extra(self, seed: int, boxes: Sequence[TargetBox], mesh_names: Sequence[str],
                   seg_base: int, depth_noise: bool) -> dict[str, Any]:
        """The extra top-level JSON keys written beside the project-format annotation:
        ``cuboid`` (one target object: its class and box; several: a list of them, in the
        order the objects were given) and ``synth``."""
        cuboids = [{"class": b.class_name, "size_m": [float(v) for v in b.size],
                    "center_m": [float(v) for v in b.center],
                    "frame": "mesh (axis-aligned bounding box)"} for b in boxes]
        return {
            "cuboid": cuboids[0] if len(cuboids) == 1 else cuboids,
            "synth": {
                "generator": GENERATOR_NAME, "version": __version__, "seed": int(seed),
                "index": int(self.index), "mesh": mesh_names[0] if len(mesh_names) == 1 else list(mesh_names),
                "depth_noise": bool(depth_noise),
                "seg_ids": {"background": 0, "targets": "instance_id (1..k)",
                            "distractors": f"{seg_base} + j (j = 1..)"},
                "bbox": "visible pixels; inclusive pixel-centre coordinates (x_min, y_min) / (x_max, y_max)",
                "visibility": "visible pixels / pixels of the instance rendered alone, whole object "
                              "(occlusion and truncation)",
                "distractor_count": sum(o.role != "target" for o in self.scene.objects),
                "instances": [asdict(s) for s in self.stats],
                **({"procedural": {"category": self.category,
                                   "labels": "canonical pose of the category's symmetries"}}
                   if self.category is not None else {}),
            },
        }


class FrameGenerator:
    """Renders frames of one or several target objects, or of a new procedural object per
    frame (one OpenGL context; one per process).

    Args:
        mesh_path: target mesh (HOPE OBJ in cm, BOP PLY in mm; see io.meshes.load_mesh), or
            several (each frame draws which of them appear: scene.sample_targets); None with
            ``procedural``.
        size: (W, H) or "WxH".
        config: the synth settings (:func:`~dope_hope.synth.settings.load_synth_config`'s), or
            what that function loads them from: a config name, path or dict of overrides.
        class_name: annotation class, one per mesh (default: the class the file names,
            io.models_dir.mesh_class_name); class names must differ (case-insensitive).
        units: mesh file units override ("m", "cm", "mm"): one for every mesh, or one per mesh.
        backgrounds: background photos, a folder or image file or several of either
            (default: procedural backgrounds).
        distractors: folder of distractor meshes (default: procedural primitives only).
        depth_noise: apply RealSense-like noise to the depth that is returned as ``depth``.
        seed: dataset seed (frame i uses SeedSequence([seed, i])).
        procedural: a new object per frame (:mod:`dope_hope.synth.objects`, the config's
            ``procedural`` section) instead of ``mesh_path``: pretraining data.
    """

    def __init__(self, mesh_path: str | os.PathLike | Sequence[str | os.PathLike] | None,
                 size: tuple[int, int] | str = (640, 480),
                 config: str | os.PathLike | dict | SectionSettings | None = None,
                 class_name: str | Sequence[str] | None = None,
                 units: str | Sequence[str | None] | None = None,
                 backgrounds: str | os.PathLike | Sequence[str | os.PathLike] | None = None,
                 distractors: str | os.PathLike | None = None, depth_noise: bool = False,
                 seed: int = 0, procedural: bool = False):
        self.size = parse_size(size)
        self.cfg = load_synth_config(config)
        self.seed = int(seed)
        self.procedural = bool(procedural)
        if self.procedural == (mesh_path is not None):
            raise ConfigError("give a target mesh or procedural objects, not both" if self.procedural
                              else "no target: give a mesh or procedural objects")
        self.targets: list[MeshAsset] = []
        if self.procedural:
            if class_name is not None and not isinstance(class_name, str):
                raise ConfigError("--class-name: --procedural objects have one class")
            self.class_names = [class_name or str(self.cfg.procedural.class_name)]
        else:
            self.targets = load_targets(mesh_path, class_name, units)
            self.class_names = [t.name for t in self.targets]
        self.class_name = self.class_names[0]
        self.target = self.targets[0] if self.targets else None
        self.library = None
        if distractors is not None:
            files = list_distractor_meshes(distractors, mesh_path, self.class_names)
            d = self.cfg.distractors
            self.library = DistractorLibrary(files, d.mesh_cache, d.max_texture_px)
        self.backgrounds = BackgroundSource(self.cfg.background, backgrounds)
        self.depth_noise = bool(depth_noise)
        self._renderer = None
        self._meshes = None

    # -- rendering resources, created on first use (in the process that renders)
    def _ensure_renderer(self) -> None:
        if self._renderer is None:
            from dope_hope.synth.materials import MeshBuilder  # noqa: PLC0415 (OpenGL starts with the first render, not with the generator)
            from dope_hope.synth.render import SceneRenderer  # noqa: PLC0415 (OpenGL starts with the first render, not with the generator)

            self._renderer = SceneRenderer(*self.size, shadows=bool(self.cfg.lights.shadows))
            self._meshes = MeshBuilder()

    def close(self) -> None:
        """Release the OpenGL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
            self._meshes = None

    def __enter__(self) -> FrameGenerator:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _target_looks(self, targets: list[MeshAsset]) -> list[TargetLook]:
        """The targets' sizes, shape classes and colours (for the hard negatives); the fixed
        targets' made once, a procedural target's per frame."""
        if targets is not self.targets:
            return [TargetLook.of(t.mesh, t.texture, t.colors, t.cuboid_size) for t in targets]
        if getattr(self, "_looks", None) is None:
            self._looks = [TargetLook.of(t.mesh, t.texture, t.colors, t.cuboid_size) for t in targets]
        return self._looks

    def dataset_info(self, gen_kwargs: dict[str, Any]) -> dict[str, Any]:
        """The dataset settings (:func:`dataset_info`) of this generator's targets: single
        values for one target object (or procedural objects), lists for several."""
        t = self.targets
        if len(t) > 1:
            return dataset_info(gen_kwargs, self.cfg, self.class_names, [a.cuboid_size for a in t],
                                [a.cuboid_center for a in t])
        return dataset_info(gen_kwargs, self.cfg, self.class_name, t[0].cuboid_size if t else None,
                            t[0].cuboid_center if t else None)

    def boxes(self, targets: list[MeshAsset]) -> list[TargetBox]:
        """Class and cuboid of each target object (the annotation's)."""
        return [TargetBox(name, t.cuboid_size, t.cuboid_center) for name, t in zip(self.class_names, targets)]

    def sample_scene(self, index: int, seed: int | None = None, force_occluder: int | None = None
                     ) -> tuple[SceneSpec, dict[str, np.random.Generator], list[MeshAsset], str | None]:
        """The random scene of frame ``index`` (no rendering), its remaining random streams, its
        target assets (``ObjectSpec.target_index`` order) and (procedural objects) the
        target's category."""
        streams = frame_streams(self.seed if seed is None else seed, index)
        targets, category = self.targets, None
        if self.procedural:
            from dope_hope.synth.objects import sample_object  # noqa: PLC0415 (procedural objects (trimesh) only for --procedural)

            p = self.cfg.procedural
            obj = sample_object(streams["object"], p.categories.to_dict(), float(p.size_jitter),
                                int(p.texture_px), name=self.class_name,
                                scale=(float(p.scale[0]), float(p.scale[1])))
            targets, category = [obj.asset], obj.category
        n_lib = len(self.library) if self.library is not None else 0
        shapes = targets[0].shape if len(targets) == 1 else [t.shape for t in targets]
        looks = self._target_looks(targets)
        spec = sample_scene(streams, self.size, self.cfg, shapes, n_lib,
                            self.library.shape if self.library is not None else None,
                            force_occluder=force_occluder, target_look=looks[0] if len(looks) == 1 else looks)
        return spec, streams, targets, category

    def render_frame(self, index: int, seed: int | None = None, force_occluder: int | None = None,
                     with_alone_depth: bool = False) -> SynthFrame:
        """Render frame ``index`` in memory.

        Args:
            index: frame index.
            seed: dataset seed (default: the generator's).
            force_occluder: target instance (list index) that gets an occluder placed in front;
                the rest of the frame is unchanged (separate random stream).
            with_alone_depth: also return each target's depth rendered alone.
        """
        self._ensure_renderer()
        spec, streams, targets, category = self.sample_scene(index, seed, force_occluder)
        target = targets[0]
        W, H = self.size
        out = self._renderer.render(spec, lambda obj: self._meshes.object_mesh(obj, targets, self.library),
                                    lambda obj: (targets[obj.target_index].cuboid_size,
                                                 targets[obj.target_index].cuboid_center),
                                    with_alone_depth=with_alone_depth)
        background = self.backgrounds.sample(streams["background"], W, H)
        rgb = composite(background, out.color, out.alpha)
        rgb = post_process(streams["post"], rgb, self.cfg.post)
        depth = out.depth
        if self.depth_noise:
            depth = add_realsense_noise(out.depth, rgb, spec.K, streams["depth_noise"],
                                        **noise_kwargs(self.cfg.depth_noise))
        labelled = spec
        if category is not None and self.cfg.procedural.canonical_labels:
            labelled = canonical_pose_labels(spec, category, target.cuboid_size)
        annotation, stats = annotate_frame(labelled, out, self.boxes(targets))
        return SynthFrame(index=int(index), rgb=rgb, depth=depth, depth_clean=out.depth, seg=out.seg,
                          annotation=annotation, stats=stats, scene=spec, alone_depth=out.alone_depth,
                          target=target, category=category, targets=list(targets))

    def json_extra(self, frame: SynthFrame, seed: int | None = None) -> dict[str, Any]:
        targets = frame.targets or [frame.target]
        names = ["procedural"] if frame.category is not None else [t.path.name for t in targets]
        return frame.json_extra(self.seed if seed is None else seed, self.boxes(targets), names,
                                int(self.cfg.output.seg_distractor_base), self.depth_noise)

    def write_frame(self, out_dir: str | os.PathLike, index: int) -> Path:
        """Render frame ``index`` and write it (images first, JSON last)."""
        frame = self.render_frame(index)
        return write_frame(out_dir, index, frame.rgb, frame.depth, frame.seg, frame.annotation,
                           extra=self.json_extra(frame))


def load_targets(mesh_path: str | os.PathLike | Sequence[str | os.PathLike],
                 class_name: str | Sequence[str] | None = None,
                 units: str | Sequence[str | None] | None = None) -> list[MeshAsset]:
    """The target meshes (one path or several), each named by its ``class_name`` entry or the
    class its file names; ``units`` one for all or one per mesh.

    Raises:
        ConfigError: class names or units not one per mesh; two targets of one class.
    """
    paths = [mesh_path] if isinstance(mesh_path, (str, os.PathLike)) else list(mesh_path)
    if not paths:
        raise ConfigError("no target: give a mesh or procedural objects")
    names = [None] * len(paths) if class_name is None else \
        [class_name] if isinstance(class_name, str) else list(class_name)
    unit_list = [units] * len(paths) if units is None or isinstance(units, str) else list(units)
    if len(unit_list) == 1:
        unit_list = unit_list * len(paths)
    if len(names) != len(paths):
        raise ConfigError(f"--class-name: {len(names)} name(s) for {len(paths)} mesh(es); give one per mesh")
    if len(unit_list) != len(paths):
        raise ConfigError(f"--units: {len(unit_list)} value(s) for {len(paths)} meshes; give one, or one per mesh")
    names = [n or guess_class_name(p) for n, p in zip(names, paths)]
    seen: dict[str, str] = {}
    for name, path in zip(names, paths):
        if name.lower() in seen:
            raise ConfigError(f"--mesh {path}: class {name!r} is also the class of {seen[name.lower()]}; "
                              "give each mesh its own --class-name")
        seen[name.lower()] = str(path)
    return [MeshAsset.load(p, name=n, units=u) for p, n, u in zip(paths, names, unit_list)]


def render_frame(mesh_path: str | os.PathLike, index: int = 0, seed: int = 0,
                 size: tuple[int, int] | str = (640, 480), config: str | os.PathLike | dict | SectionSettings | None = None,
                 force_occluder: int | None = None, **kwargs: Any) -> SynthFrame:
    """One frame in memory (loads the mesh and opens a renderer: for many frames keep a
    :class:`FrameGenerator`). ``kwargs`` go to FrameGenerator (class_name, backgrounds, ...)."""
    with FrameGenerator(mesh_path, size=size, config=config, seed=seed, **kwargs) as gen:
        return gen.render_frame(index, force_occluder=force_occluder)


def _one_or_list(value: Any) -> Any:
    """A string or None as it is; a sequence of one value as that value; else a list (the
    settings of a one-object dataset keep their single values)."""
    if value is None or isinstance(value, str):
        return value
    values = list(value)
    return values[0] if len(values) == 1 else values


def photo_paths(photos: str | os.PathLike | Sequence[str | os.PathLike] | None) -> str | list[str] | None:
    """``backgrounds`` (or the target meshes) as plain strings for the worker processes and the
    dataset's settings: one path stays a string (the settings file of a one-folder / one-mesh
    dataset is the same as before several were allowed), several become a list."""
    if photos is None:
        return None
    if isinstance(photos, (str, os.PathLike)):
        return str(photos)
    paths = [str(p) for p in photos]
    return paths[0] if len(paths) == 1 else paths


def dataset_info(gen_kwargs: dict[str, Any], cfg: SectionSettings, class_name: str | list[str],
                 cuboid_size: np.ndarray | list[np.ndarray] | None,
                 cuboid_center: np.ndarray | list[np.ndarray] | None) -> dict[str, Any]:
    """Settings that define a dataset's frames (must match when resuming or adding shards);
    procedural objects have no dataset-wide cuboid (None: each frame's JSON records its own).
    Several target objects: ``class``, ``mesh`` and the cuboid entries are lists (one target
    object: single values, as the settings of a one-object dataset always were)."""
    def vec(v):
        if v is None:
            return None
        if isinstance(v, list):
            return [vec(x) for x in v]
        return [float(x) for x in v]

    def name(p):
        if isinstance(p, list):
            return [Path(q).name for q in p]
        return None if p is None else Path(p).name

    return {"generator": GENERATOR_NAME, "version": __version__, "class": class_name,
            "mesh": "procedural" if gen_kwargs.get("procedural") else name(gen_kwargs["mesh_path"]),
            "units": gen_kwargs.get("units"),
            "seed": int(gen_kwargs["seed"]), "size": list(parse_size(gen_kwargs["size"])),
            "backgrounds": name(gen_kwargs.get("backgrounds")),
            "distractors": name(gen_kwargs.get("distractors")),
            "depth_noise": bool(gen_kwargs.get("depth_noise")),
            "cuboid_size_m": vec(cuboid_size), "cuboid_center_m": vec(cuboid_center),
            "config": cfg.to_dict()}


@dataclass(frozen=True)
class SynthJob:
    """What a dataset's frames are made of: the :class:`FrameGenerator` arguments (see there),
    one object as training's ``TrainJob``. Frame ``i`` depends only on these and ``i``."""

    mesh_path: str | os.PathLike | Sequence[str | os.PathLike] | None
    seed: int = 0
    size: tuple[int, int] | str = (640, 480)
    config: str | os.PathLike | dict | SectionSettings | None = None
    class_name: str | Sequence[str] | None = None
    units: str | Sequence[str | None] | None = None
    backgrounds: str | os.PathLike | Sequence[str | os.PathLike] | None = None
    distractors: str | os.PathLike | None = None
    depth_noise: bool = False
    procedural: bool = False

    def generator_kwargs(self) -> dict[str, Any]:
        """The FrameGenerator's keyword arguments as plain values (picklable for the worker
        processes; one mesh / photo folder / class stays a single value, as a one-object
        dataset's settings always were)."""
        return dict(mesh_path=photo_paths(self.mesh_path), size=parse_size(self.size), config=self.config,
                    class_name=_one_or_list(self.class_name), units=_one_or_list(self.units),
                    backgrounds=photo_paths(self.backgrounds),
                    distractors=None if self.distractors is None else str(self.distractors),
                    depth_noise=bool(self.depth_noise), seed=int(self.seed), procedural=bool(self.procedural))
