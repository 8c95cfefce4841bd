"""Dataset layouts: which annotation an image has, and which layout a dataset folder follows.

The one detector of ``dope-hope infer`` (an image's camera from its sibling annotation,
:func:`dope_hope.io.camera.find_image_camera`) and ``dope-hope evaluate`` (the ground truth
of a dataset folder, :func:`dataset_layout`). Layouts, tried in this order for ``DIR/NAME``:

- ``dope``: ``DIR/<stem>.json`` (``000123.png`` -> ``000123.json``; :mod:`dope_hope.io.dope_json`);
- ``hope``: ``DIR/NNNN.json`` for ``NNNN_rgb.jpg`` / ``.png`` (:mod:`dope_hope.io.hope_json`);
- ``bop``: ``SCENE/scene_camera.json`` for ``SCENE/rgb/NNNNNN.png`` (or ``gray/``;
  :mod:`dope_hope.io.bop`).
"""
from __future__ import annotations

import os
import re
from pathlib import Path

from dope_hope.errors import InputFileError
from dope_hope.io.bop import list_bop_scenes
from dope_hope.io.images import is_colour_image

#: The layouts, in the order an image's annotation is looked for.
LAYOUTS = ("dope", "hope", "bop")
_HOPE_RGB = re.compile(r"^(?P<stem>.+)_rgb\.(jpg|jpeg|png)$", re.IGNORECASE)
#: Image folders of a BOP scene.
BOP_IMAGE_FOLDERS = ("rgb", "gray")


def annotation_file(image: str | os.PathLike, layout: str) -> Path | None:
    """The annotation file of ``image`` in ``layout`` (module docstring), if it exists."""
    image = Path(image)
    if layout == "dope":
        ann = image.with_suffix(".json")
    elif layout == "hope":
        m = _HOPE_RGB.match(image.name)
        if m is None:
            return None
        ann = image.with_name(m.group("stem") + ".json")
    elif layout == "bop":
        if image.parent.name not in BOP_IMAGE_FOLDERS or not image.stem.isdigit():
            return None
        ann = image.parent.parent / "scene_camera.json"
    else:
        raise ValueError(f"unknown layout {layout!r}; known: {', '.join(LAYOUTS)}")
    return ann if ann.is_file() else None


def image_layout(image: str | os.PathLike) -> str | None:
    """The first layout in :data:`LAYOUTS` in which ``image`` has an annotation, or None."""
    return next((layout for layout in LAYOUTS if annotation_file(image, layout) is not None), None)


def annotation_search_description(image: str | os.PathLike) -> str:
    """The annotation files looked for beside ``image`` (for error messages)."""
    image = Path(image)
    names = [image.with_suffix(".json").name]
    m = _HOPE_RGB.match(image.name)
    if m is not None:
        names.append(m.group("stem") + ".json")
    if image.parent.name in BOP_IMAGE_FOLDERS:
        names.append("../scene_camera.json")
    return ", ".join(names)


def dataset_layout(root: str | os.PathLike) -> str:
    """The layout of a dataset folder: "bop" for a BOP split folder (scene folders with a
    ``scene_camera.json``) or a BOP dataset folder with a ``test/`` split; else the layout of
    the first image (folders and files in sorted order, the folder itself first) that has an
    annotation.

    Raises:
        InputFileError: the folder is missing or holds no annotated image of any layout.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputFileError(root, "dataset folder not found")
    if list_bop_scenes(root) or ((root / "test").is_dir() and list_bop_scenes(root / "test")):
        return "bop"
    for folder in [root] + sorted(p for p in root.rglob("*") if p.is_dir()):
        for image in sorted(p for p in folder.iterdir() if p.is_file() and is_colour_image(p)):
            layout = image_layout(image)
            if layout is not None:
                return layout
    raise InputFileError(root, "no annotated frames found: no image with a DOPE (<stem>.json), HOPE "
                               "(NNNN_rgb.jpg + NNNN.json) or BOP (scene_camera.json) annotation")
