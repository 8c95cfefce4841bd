"""A camera moving through one static scene: the generator's scene of one frame seen from a
camera path around its target, frame after frame, with depth (RealSense-like noise when the
generator adds it) and the annotation of each view: the sequences a robot's camera records.

:func:`orbit_poses` gives the camera path (a sweep about the target's centre, the camera
turning left-right about its up axis and rising slightly, always looking at the target);
:class:`TrajectoryRenderer` renders the sequence: the scene of ``FrameGenerator.sample_scene``
(objects, lights, materials and the backdrop photo fixed), moved into each view's camera frame
(the scene moves by the inverse of the camera's motion), rendered, composited over the
backdrop, post-processed with the generator's own steps and annotated as the generator
annotates.
"""
from __future__ import annotations

from collections.abc import Iterator
from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from dope_hope.synth.annotate import annotate_frame
from dope_hope.synth.depth_noise import add_realsense_noise, noise_kwargs
from dope_hope.synth.generate import FrameGenerator, SynthFrame
from dope_hope.synth.postprocess import composite, post_process
from dope_hope.synth.scene import LightSpec, ObjectSpec, SceneSpec


def orbit_poses(frames: int, sweep_deg: float = 40.0, rise_deg: float = 10.0) -> list[np.ndarray]:
    """(4, 4) rigid motions M_k of the scene in the first camera's frame, k = 0..frames-1 (M_0 =
    identity): the scene turned about the camera's up axis (y) by a sweep from 0 to
    ``sweep_deg`` and about its x axis by up to ``rise_deg`` (a sine), both about the origin;
    :meth:`TrajectoryRenderer.sequence` applies them about the target's centre."""
    out = []
    for k in range(frames):
        s = k / max(frames - 1, 1)
        R = Rotation.from_euler("yx", [sweep_deg * s, rise_deg * np.sin(np.pi * s)], degrees=True).as_matrix()
        M = np.eye(4)
        M[:3, :3] = R
        out.append(M)
    return out


def _about(M: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """The motion ``M`` (4, 4) applied about ``centre`` (3,) instead of the origin."""
    T = np.eye(4)
    T[:3, :3] = M[:3, :3]
    T[:3, 3] = centre - M[:3, :3] @ centre + M[:3, 3]
    return T


def _moved_object(o: ObjectSpec, T: np.ndarray) -> ObjectSpec:
    R, t = T[:3, :3], T[:3, 3]
    return replace(o, R=R @ o.R, t=R @ o.t + t, center=R @ o.center + t)


def _moved_light(light: LightSpec, T: np.ndarray) -> LightSpec:
    R, t = T[:3, :3], T[:3, 3]
    return replace(light, position=R @ light.position + t, direction=R @ light.direction)


class TrajectoryRenderer:
    """Sequences of one generator's scenes seen by a moving camera (module docstring).

    Args:
        generator: the :class:`FrameGenerator` whose scenes, backdrops, post-processing and
            depth noise the sequences use (its size, config and meshes); its own renderer is
            not used (one OpenGL context per process: this one's).
    """

    def __init__(self, generator: FrameGenerator):
        self.gen = generator
        self._renderer = None
        self._meshes = None

    def close(self) -> None:
        """Release the OpenGL context."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = self._meshes = None

    def __enter__(self) -> TrajectoryRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def sequence(self, scene_index: int, frames: int, seed: int | None = None, sweep_deg: float = 40.0,
                 rise_deg: float = 10.0) -> Iterator[SynthFrame]:
        """The ``frames`` views of scene ``scene_index`` (the generator's frame of that index and
        ``seed``) along :func:`orbit_poses` about its first target's centre, as
        :class:`SynthFrame` s (``index`` the view's; ``depth`` noisy when the generator adds
        noise). Views are drawn in order; each view's post-processing and noise draw from
        streams of (seed, scene_index, view)."""
        if self._renderer is None:  # OpenGL starts with the first render
            from dope_hope.synth.materials import MeshBuilder  # noqa: PLC0415 (OpenGL starts with the first render)
            from dope_hope.synth.render import SceneRenderer  # noqa: PLC0415 (OpenGL starts with the first render)

            W, H = self.gen.size
            self._renderer = SceneRenderer(W, H, shadows=bool(self.gen.cfg.lights.shadows))
            self._meshes = MeshBuilder()
        seed = self.gen.seed if seed is None else int(seed)
        spec, streams, targets, _ = self.gen.sample_scene(scene_index, seed)
        W, H = self.gen.size
        backdrop = self.gen.backgrounds.sample(streams["background"], W, H)
        centre = spec.targets[0].center if spec.targets else np.array([0.0, 0.0, 1.0])
        boxes = self.gen.boxes(targets)
        for k, M in enumerate(orbit_poses(frames, sweep_deg, rise_deg)):
            T = _about(M, np.asarray(centre, np.float64))
            view = SceneSpec(spec.width, spec.height, spec.K, spec.znear, spec.zfar,
                             [_moved_object(o, T) for o in spec.objects], [_moved_light(li, T) for li in spec.lights],
                             spec.ambient, spec.target_material)
            out = self._renderer.render(view, lambda o: self._meshes.object_mesh(o, targets, self.gen.library),
                                        lambda o: (targets[o.target_index].cuboid_size,
                                                   targets[o.target_index].cuboid_center))
            rng = np.random.default_rng([seed, int(scene_index), k])
            rgb = post_process(rng, composite(backdrop, out.color, out.alpha), self.gen.cfg.post)
            depth = out.depth
            if self.gen.depth_noise:
                depth = add_realsense_noise(out.depth, rgb, view.K, rng, **noise_kwargs(self.gen.cfg.depth_noise))
            annotation, stats = annotate_frame(view, out, boxes)
            yield SynthFrame(index=k, rgb=rgb, depth=depth, depth_clean=out.depth, seg=out.seg,
                             annotation=annotation, stats=stats, scene=view, target=targets[0],
                             targets=list(targets))
