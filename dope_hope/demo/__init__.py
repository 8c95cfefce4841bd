"""`dope-hope demo` as a library: the demo's scenes, its ONNX cache, its scoring and its run.

- ``scenes``: the demo's scene distribution (configs/demo.yaml at 640x480) and
  :func:`~dope_hope.demo.scenes.render_scene`, which redraws a scene until the box is at least
  half visible, so that the demo's count measures the model, not the scene.
- ``onnx_cache``: the demo weights exported once to ONNX, reused while they are unchanged.
- ``report``: one scene's detections scored as ``dope-hope evaluate`` scores them
  (evaluation.matching), the per-scene lines and the summary.
- ``run``: :func:`~dope_hope.demo.run.run_demo`, the whole demo (render, both backends, -LS,
  ICP, overlays, predictions), its lines handed to the caller to print.

The demo box itself is :mod:`dope_hope.demo_object`. The package sits just below
``commands/``: it uses synth, inference, refine, evaluation, export, io and viz.
"""
