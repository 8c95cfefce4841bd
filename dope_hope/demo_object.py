"""The embedded demo object: a procedurally generated, textured cereal-style box.

It stands in for a HOPE cuboid (sized like HOPE's Cookies box: 12.27 x 16.72 x 4.02 cm in the
mesh frame, y vertical) and is built entirely by this module — no third-party mesh or texture
ships with dope-hope. Every face carries its own colour and pattern (a banner on the front,
stripes on the back, numbered side panels, marked top and bottom), so the label fixes the
box's rotation; only the geometric symmetries of the cuboid remain for the metrics. They are
declared like any custom object's (:mod:`dope_hope.io.symmetries`): ``model_info.json`` beside
the written mesh, so the demo, training labels and the evaluation read the same declaration.
"""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import trimesh

from dope_hope.io.atomic import atomic_path, atomic_write_text
from dope_hope.io.symmetries import DECLARATION_NAMES, SymmetryDeclaration

DEMO_CLASS_NAME = "DemoBox"
#: (3,) extents in the mesh frame (x width, y vertical, z depth), metres.
DEMO_SIZE_M = np.array([0.1227, 0.1672, 0.0402])
#: The box's symmetry declaration (BOP fields): the 180-degree turns about x, y and z.
DEMO_SYMMETRIES = {"symmetries_discrete": [
    [1, 0, 0, 0, 0, -1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
    [-1, 0, 0, 0, 0, 1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1],
    [-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]]}


def demo_symmetries() -> SymmetryDeclaration:
    """:data:`DEMO_SYMMETRIES` as a declaration (lengths in metres; all translations are 0)."""
    return SymmetryDeclaration(DEMO_SYMMETRIES, "m", "dope_hope.demo_object")

_TILE = 256  # texture pixels per atlas tile
# Faces as (outward normal axis, sign, atlas tile (col, row), base colour RGB).
_FACES = (
    ("z", +1, (0, 0), (220, 40, 40)),    # front: red with a banner
    ("z", -1, (1, 0), (40, 90, 200)),    # back: blue with stripes
    ("x", +1, (2, 0), (40, 170, 70)),    # right: green panel "1"
    ("x", -1, (0, 1), (240, 200, 30)),   # left: yellow panel "2"
    ("y", +1, (1, 1), (245, 245, 245)),  # top: white with a black bar
    ("y", -1, (2, 1), (60, 60, 60)),     # bottom: dark grey with a circle
)


def _face_texture(index: int, colour: tuple[int, int, int]) -> np.ndarray:
    """(T, T, 3) uint8 RGB pattern of one face; deterministic and asymmetric."""
    t = _TILE
    img = np.empty((t, t, 3), np.uint8)
    img[:] = colour
    dark, light = (20, 20, 20), (255, 255, 255)
    if index == 0:  # front: banner across the upper third, text, a corner triangle
        cv2.rectangle(img, (0, t // 6), (t - 1, t // 3), light, -1)
        cv2.putText(img, "DOPE", (t // 8, int(t * 0.30)), cv2.FONT_HERSHEY_SIMPLEX, 1.6, dark, 4)
        cv2.fillPoly(img, [np.array([[0, t - 1], [t // 3, t - 1], [0, 2 * t // 3]])], dark)
        cv2.circle(img, (3 * t // 4, 2 * t // 3), t // 8, (250, 220, 0), -1)
    elif index == 1:  # back: diagonal stripes, one thick bar at the top
        for k in range(-t, t, 40):
            cv2.line(img, (k, 0), (k + t, t), light, 8)
        cv2.rectangle(img, (0, 0), (t - 1, t // 8), dark, -1)
    elif index in (2, 3):  # sides: big digit and a bar on one edge
        cv2.putText(img, str(index - 1), (t // 4, 3 * t // 4), cv2.FONT_HERSHEY_SIMPLEX, 5.0, dark, 14)
        cv2.rectangle(img, (0, 0), (t // 10, t - 1), light, -1)
    elif index == 4:  # top: off-centre black bar
        cv2.rectangle(img, (t // 10, t // 5), (t // 2, t // 3), dark, -1)
        cv2.circle(img, (3 * t // 4, 3 * t // 4), t // 10, (220, 40, 40), -1)
    else:  # bottom: ring and a light square in one corner
        cv2.circle(img, (t // 2, t // 2), t // 4, light, 10)
        cv2.rectangle(img, (2 * t // 3, 0), (t - 1, t // 3), light, -1)
    return img


def demo_texture() -> np.ndarray:
    """(2T, 3T, 3) uint8 RGB texture atlas: 3 columns x 2 rows of face tiles."""
    atlas = np.zeros((2 * _TILE, 3 * _TILE, 3), np.uint8)
    for i, (_, _, (col, row), colour) in enumerate(_FACES):
        atlas[row * _TILE:(row + 1) * _TILE, col * _TILE:(col + 1) * _TILE] = _face_texture(i, colour)
    return atlas


def _face_quad(axis: str, sign: int, half: np.ndarray) -> np.ndarray:
    """(4, 3) corners of one face, counter-clockwise seen from outside; first corner maps to
    the tile's bottom-left texel (uv (0, 0))."""
    a = "xyz".index(axis)
    u_axis, v_axis = {0: (2, 1), 1: (0, 2), 2: (0, 1)}[a]
    # Choose the in-plane u direction so that (u, v, normal) is right-handed.
    u_dir = np.zeros(3)
    v_dir = np.zeros(3)
    n = np.zeros(3)
    n[a] = sign
    v_dir[v_axis] = 1.0
    u_dir[u_axis] = 1.0
    if np.dot(np.cross(u_dir, v_dir), n) < 0:
        u_dir = -u_dir
    centre = n * half[a]
    hu, hv = half[u_axis], half[v_axis]
    return np.array([centre - u_dir * hu - v_dir * hv, centre + u_dir * hu - v_dir * hv,
                     centre + u_dir * hu + v_dir * hv, centre - u_dir * hu + v_dir * hv])


def demo_object_mesh() -> trimesh.Trimesh:
    """The demo box as a textured trimesh in metres, centred on its bounding box."""
    half = DEMO_SIZE_M / 2.0
    vertices, faces, uvs = [], [], []
    for i, (axis, sign, (col, row), _) in enumerate(_FACES):
        quad = _face_quad(axis, sign, half)
        base = 4 * i
        vertices.append(quad)
        faces += [[base, base + 1, base + 2], [base, base + 2, base + 3]]
        # Atlas uv: origin at the bottom-left of the image (OBJ convention), 3 x 2 tiles,
        # with a half-texel inset so that filtering never bleeds across tiles.
        eps = 0.5 / _TILE
        u0, u1 = (col + eps) / 3.0, (col + 1 - eps) / 3.0
        v0, v1 = 1.0 - (row + 1 - eps) / 2.0, 1.0 - (row + eps) / 2.0
        uvs.append([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=_to_pil(demo_texture()), metallicFactor=0.0, roughnessFactor=0.8)
    visual = trimesh.visual.TextureVisuals(uv=np.concatenate(uvs), material=material)
    return trimesh.Trimesh(vertices=np.concatenate(vertices), faces=np.array(faces),
                           visual=visual, process=False)


def _to_pil(rgb: np.ndarray):
    from PIL import Image  # noqa: PLC0415 (Pillow only to write the texture)

    return Image.fromarray(rgb)


def write_demo_object(out_dir: str | Path) -> Path:
    """Write the demo box as ``DemoBox.obj`` (+ .mtl and texture PNG) in centimetres, the
    HOPE convention, so that every mesh-taking command accepts it, and its symmetry
    declaration as ``model_info.json`` beside it. Returns the OBJ path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    obj_path = out_dir / f"{DEMO_CLASS_NAME}.obj"
    mesh = demo_object_mesh()
    mesh_cm = mesh.copy()
    mesh_cm.apply_scale(100.0)
    files = trimesh.exchange.obj.export_obj(mesh_cm, include_texture=True, return_texture=True,
                                            mtl_name=f"{DEMO_CLASS_NAME}.mtl")
    text, extra = files
    for name, data in extra.items():
        with atomic_path(out_dir / name) as tmp:
            tmp.write_bytes(data)
    with atomic_path(obj_path) as tmp:
        tmp.write_text("# dope-hope demo box, centimetres\n" + text)
    atomic_write_text(out_dir / DECLARATION_NAMES[0], json.dumps(DEMO_SYMMETRIES) + "\n")
    return obj_path
