"""Domain-randomized synthetic data for one object (pyrender, headless EGL).

Modules, one job each:

- ``settings``: the synth config (configs/synth.yaml + user overrides) as frozen settings
  objects, read as attributes; sizes, shards.
- ``camera``: reference intrinsics scaled to the image size, jittered.
- ``textures`` / ``background``: procedural images; background photo crops.
- ``clutter``: table-top clutter drawn over backgrounds (2D, no OpenGL).
- ``primitives``: procedural distractor shapes with texture coordinates.
- ``hard_negatives``: look-alikes of the target (its size, shape class and colours).
- ``assets``: target / distractor meshes (via io.meshes), cuboid, models-folder lookup.
- ``scene``: per-frame random streams and scene sampling (pure numpy).
- ``materials`` / ``render``: pyrender meshes, materials and the render passes.
- ``postprocess``: compositing over the background, jitter, blur, noise.
- ``sensor``: colour-camera artefacts (defocus, motion blur, chromatic aberration, vignetting,
  exposure, white balance, shot/read noise, JPEG).
- ``depth_noise``: RealSense-like depth corruption (:func:`add_realsense_noise`).
- ``annotate``: projected cuboids, visibility, boxes -> FrameAnnotation.
- ``writer``: frame files (JSON last, atomic) and the dataset info file.
- ``generate``: FrameGenerator / render_frame (in memory), SynthJob (a dataset's frame settings).
- ``to_disk``: generate_dataset (to disk: resumable, sharded); ``pool``: its worker processes;
  ``preview``: preview.png of the written frames.

Importing this package does not import OpenGL; rendering starts it on first use.
"""
from dope_hope.synth.depth_noise import add_realsense_noise
from dope_hope.synth.generate import FrameGenerator, SynthFrame, SynthJob, render_frame
from dope_hope.synth.to_disk import GenerateSummary, generate_dataset

__all__ = ["FrameGenerator", "GenerateSummary", "SynthFrame", "SynthJob", "add_realsense_noise", "generate_dataset",
           "render_frame"]
