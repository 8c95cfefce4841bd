"""pyrender meshes and materials for the generator's objects.

The target gets a ``MetallicRoughnessMaterial`` with metallic 0 and its texture as
``baseColorTexture``: trimesh's default for OBJ textures (base colour 0.4, metallic 1.0)
renders the HOPE scans almost black. All materials are opaque (no alpha blending), so that
draw order never matters and the alpha channel is pure coverage.
"""
from __future__ import annotations

import numpy as np
import trimesh

from dope_hope.render.gl import import_pyrender
from dope_hope.synth.assets import MeshAsset
from dope_hope.synth.scene import MaterialSpec, ObjectSpec

pyrender = import_pyrender()


def make_texture(image: np.ndarray) -> pyrender.Texture:
    """(h, w, 3|4) uint8 -> pyrender texture (mipmapped, repeating).

    An RGB image whose rows are not a multiple of 4 bytes is uploaded as RGBA (opaque):
    pyrender leaves OpenGL's unpack alignment at 4, which would skew such an image and read
    past its end (frames that depended on whatever memory followed).
    """
    img = np.ascontiguousarray(image, dtype=np.uint8)
    if img.ndim == 3 and img.shape[2] == 3 and (3 * img.shape[1]) % 4:
        img = np.concatenate([img, np.full(img.shape[:2] + (1,), 255, np.uint8)], axis=2)
    channels = "RGBA" if img.ndim == 3 and img.shape[2] == 4 else "RGB"
    return pyrender.Texture(source=img, source_channels=channels, sampler=pyrender.Sampler())


def make_material(spec: MaterialSpec, texture: pyrender.Texture | None = None) -> pyrender.MetallicRoughnessMaterial:
    """An opaque PBR material from a :class:`MaterialSpec` (and an optional texture)."""
    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=np.asarray(spec.base_color, dtype=np.float64),
        metallicFactor=float(spec.metallic),
        roughnessFactor=float(spec.roughness),
        baseColorTexture=texture,
        alphaMode="OPAQUE",
    )


def pyrender_primitive(mesh: trimesh.Trimesh, material: pyrender.MetallicRoughnessMaterial,
                       use_uv: bool = True, colors: np.ndarray | None = None) -> pyrender.Primitive:
    """A pyrender primitive with the mesh's smooth normals, uv and (optionally) vertex colours."""
    uv = getattr(mesh.visual, "uv", None) if use_uv else None
    return pyrender.Primitive(
        positions=np.asarray(mesh.vertices, dtype=np.float32),
        normals=np.asarray(mesh.vertex_normals, dtype=np.float32),
        texcoord_0=None if uv is None else np.asarray(uv, dtype=np.float32),
        color_0=None if colors is None else np.asarray(colors, dtype=np.float32) / 255.0,
        indices=np.asarray(mesh.faces, dtype=np.uint32),
        material=material,
    )


class MeshBuilder:
    """Builds the pyrender meshes of a frame, reusing what can be reused.

    The target's geometry and texture are uploaded once per renderer and shared by all its
    instances (only the material object is swapped per frame); textures of library meshes
    are cached per file. Primitives and their procedural textures are new every frame.
    """

    def __init__(self) -> None:
        self._target_meshes: dict[str, pyrender.Mesh] = {}
        self._textures: dict[str, pyrender.Texture] = {}

    def _texture_for(self, asset: MeshAsset) -> pyrender.Texture | None:
        key = str(asset.path)
        if asset.texture is None:
            return None
        if key not in self._textures:
            self._textures[key] = make_texture(asset.texture)
        return self._textures[key]

    def target(self, asset: MeshAsset, spec: MaterialSpec) -> pyrender.Mesh:
        """The shared target mesh with this frame's material (a new one for an asset that is
        not cacheable: a procedural object)."""
        if not asset.cacheable:
            texture = make_texture(asset.texture) if asset.texture is not None else None
            material = make_material(spec, texture)
            return pyrender.Mesh(primitives=[pyrender_primitive(asset.mesh, material, use_uv=texture is not None,
                                                                colors=asset.colors)])
        key = str(asset.path)
        material = make_material(spec, self._texture_for(asset))
        if key not in self._target_meshes:
            prim = pyrender_primitive(asset.mesh, material, use_uv=asset.texture is not None,
                                      colors=asset.colors)
            self._target_meshes[key] = pyrender.Mesh(primitives=[prim])
        mesh = self._target_meshes[key]
        mesh.primitives[0].material = material
        return mesh

    def library_mesh(self, asset: MeshAsset, spec: MaterialSpec) -> pyrender.Mesh:
        """A distractor from the mesh library: own texture (tinted) or a random material."""
        has_uv = getattr(asset.mesh.visual, "uv", None) is not None
        if spec.keep_texture:
            texture = self._texture_for(asset)
            colors = asset.colors
        else:
            texture = make_texture(spec.texture) if spec.texture is not None and has_uv else None
            colors = None
        material = make_material(spec, texture)
        return pyrender.Mesh(primitives=[pyrender_primitive(asset.mesh, material, use_uv=texture is not None,
                                                            colors=colors)])

    def object_mesh(self, obj: ObjectSpec, targets: list[MeshAsset], library) -> pyrender.Mesh:
        """The mesh of one scene object: its target (``targets[obj.target_index]``), a
        distractor of ``library`` (a :class:`~dope_hope.synth.assets.DistractorLibrary`) or a
        primitive, with its material."""
        if obj.source == "target":
            return self.target(targets[obj.target_index], obj.material)
        if obj.source == "mesh":
            return self.library_mesh(library.get(obj.mesh_index), obj.material)
        return self.primitive_mesh(obj.geometry, obj.material)

    @staticmethod
    def primitive_mesh(geometry: trimesh.Trimesh, spec: MaterialSpec) -> pyrender.Mesh:
        """A procedural primitive with its random material."""
        texture = make_texture(spec.texture) if spec.texture is not None else None
        material = make_material(spec, texture)
        return pyrender.Mesh(primitives=[pyrender_primitive(geometry, material, use_uv=texture is not None)])
