"""Typed inference options: what a :class:`~dope_hope.inference.predictor.DopePredictor` does
with a model's maps (the settings of ``dope-hope infer``, ``demo`` and ``bop-submit``).

:class:`InferenceOptions` holds the top-level keys, whose defaults the packaged
``dope_hope/configs/infer.yaml`` documents and gives (the class reads them from it, so they
have one owner), and one section per stage, each the stage's settings dataclass, which sits
beside the stage's function and owns that section's defaults. Every key is checked: an
unknown key or a bad value is a ConfigError naming it.

**Presets** (:data:`PRESETS`, ``dope-hope infer --fast`` / ``--accurate``): "fast", the
packaged defaults (one working size, no turns, ICP only when asked), what a
:class:`~dope_hope.inference.predictor.DopePredictor` built without options and every stream
(video, camera, RealSense, recording, a robot node) runs: the frame rate first; "accurate",
``dope_hope/configs/infer_accurate.yaml`` over them, what still images, folders and
``bop-submit`` run by default: the settings that measure best on held-out frames (three
working sizes, ICP where there is depth and a surface to fit, the trained turns where there
is not). :func:`preset_options` puts what a user sets on top of a preset.
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from dope_hope.config import (
    SectionSettings,
    at_least,
    finite_float,
    load_config,
    merge,
    one_of,
    or_none,
    section,
)
from dope_hope.errors import ConfigError
from dope_hope.inference.appearance import AppearanceSettings
from dope_hope.inference.depth_confirm import DepthConfirmSettings
from dope_hope.inference.new_object_settings import NewObjectSettings
from dope_hope.inference.pnp import PnpSettings
from dope_hope.inference.pose_search import HypothesisSettings
from dope_hope.inference.scales import MultiscaleSettings
from dope_hope.inference.tracking_settings import TrackingSettings
from dope_hope.maps.decode import DecodeSettings
from dope_hope.preprocess import check_working_side
from dope_hope.refine.icp import IcpSettings
from dope_hope.refine.line_search import LineSearchSettings

#: Pose searches: multi-hypothesis PnP over corner candidates, or DOPE's one-to-one grouping.
POSE_SEARCHES = ("hypotheses", "groups")

#: The values of ``icp``: off, after -LS on every detection (depth required), or "auto": after
#: -LS where the image has depth and the object a surface to fit (a mesh, or a catalog box).
ICP_MODES = (False, True, "auto")
#: The inference presets (module docstring): name -> the packaged config of what it changes
#: over ``infer.yaml`` (None: nothing).
PRESETS: dict[str, str | None] = {"fast": None, "accurate": "infer_accurate"}
#: The preset of still images, folders and ``bop-submit``; of video, cameras and recordings.
STILL_IMAGE_PRESET, STREAM_PRESET = "accurate", "fast"


def icp_mode(value: Any, name: str) -> bool | str:
    """The rule of ``icp``: true, false or "auto" (:data:`ICP_MODES`)."""
    if value is True or value is False or value == "auto":
        return value
    raise ConfigError(f"{name} must be true, false or auto, got {value!r}")


def preset_options(preset: str, given: Mapping[str, Any] | None = None, *, fixed_size: bool = False,
                   new_object: bool = False, meshes: bool = True) -> dict[str, Any]:
    """The option overrides of ``preset`` (:data:`PRESETS`) with ``given`` (what the user set,
    nested as a config file writes it) on top. For a model of one input size (``fixed_size``:
    a fixed-size export) and for a new object's detector (``new_object``: its working sizes are
    ``new_object.scales``, its own turns and pose rule), the preset's working sizes (and for
    the detector its ``depth_confirm``) are left out; its
    trained turns for a new object's detector and for a model given no mesh (``meshes``
    false: they need a textured one, and a setting nobody asked for warns of nothing); what
    ``given`` sets is kept whatever it is (and checked where it is used)."""
    if preset not in PRESETS:
        raise ConfigError(f"preset: one of {', '.join(PRESETS)}, got {preset!r}")
    base = load_config(PRESETS[preset]) if PRESETS[preset] else {}
    if fixed_size or new_object:
        base.pop("multiscale", None)
    if new_object:  # its own pose rule (the appearance check), not the depth confirmation
        base.pop("depth_confirm", None)
    if new_object or not meshes:
        base.get("appearance", {}).pop("trained_turns", None)
    return merge(base, dict(given or {}))


#: The top-level defaults, as ``dope_hope/configs/infer.yaml`` gives them (its stage sections
#: are empty: their defaults are the stage classes').
TOP_LEVEL_DEFAULTS: dict[str, Any] = {k: v for k, v in load_config("infer").items() if not isinstance(v, dict)}


@dataclass(frozen=True)
class InferenceOptions(SectionSettings):
    """Inference options (see ``dope_hope/configs/infer.yaml`` for each key's meaning).

    height: working height in px or None (the model's training scale). pose_search: one of
    :data:`POSE_SEARCHES`. min_score: detections below are dropped. ls_points / icp_points:
    model points for -LS / ICP. icp: one of :data:`ICP_MODES`. decode, pnp,
    hypotheses, line_search, icp_refine, depth_confirm, tracking, appearance, new_object, multiscale: each stage's settings
    object, as its function takes it (a mapping given for one is read over its defaults):
    decode (:func:`~dope_hope.maps.decode.corner_candidates` / :func:`~dope_hope.maps.decode.decode_maps`),
    pnp (:func:`~dope_hope.inference.pnp.solve_pnp`), hypotheses
    (:func:`~dope_hope.inference.pose_search.solve_pnp_candidates`), line_search
    (:func:`~dope_hope.refine.line_search.depth_line_search`), icp_refine
    (:func:`~dope_hope.refine.icp.icp_refine`), depth_confirm (the poses under the threshold the
    depth keeps, :mod:`dope_hope.inference.depth_confirm`), tracking (the stream tracker), appearance (the
    appearance check of a new object's cuboid detector,
    :class:`~dope_hope.inference.appearance.AppearanceCheck`), new_object (that detector's working
    sizes, :class:`~dope_hope.inference.mesh_start.MeshStartPredictor`), multiscale (a trained
    model's working sizes and the pooling of every model's, :mod:`dope_hope.inference.scales`).
    """

    SECTION = ""
    RULES = {"height": or_none(check_working_side), "pose_search": one_of(*POSE_SEARCHES),
             "min_score": finite_float, "ls_points": at_least(10), "icp": icp_mode, "icp_points": at_least(10)}

    height: int | None = TOP_LEVEL_DEFAULTS["height"]
    pose_search: str = TOP_LEVEL_DEFAULTS["pose_search"]
    min_score: float = TOP_LEVEL_DEFAULTS["min_score"]
    ls_points: int = TOP_LEVEL_DEFAULTS["ls_points"]
    icp: bool | str = TOP_LEVEL_DEFAULTS["icp"]
    icp_points: int = TOP_LEVEL_DEFAULTS["icp_points"]
    decode: DecodeSettings = section(DecodeSettings)
    pnp: PnpSettings = section(PnpSettings)
    hypotheses: HypothesisSettings = section(HypothesisSettings)
    line_search: LineSearchSettings = section(LineSearchSettings)
    icp_refine: IcpSettings = section(IcpSettings)
    depth_confirm: DepthConfirmSettings = section(DepthConfirmSettings)
    tracking: TrackingSettings = section(TrackingSettings)
    appearance: AppearanceSettings = section(AppearanceSettings)
    new_object: NewObjectSettings = section(NewObjectSettings)
    multiscale: MultiscaleSettings = section(MultiscaleSettings)

    @classmethod
    def from_mapping(cls, values: Mapping[str, Any] | None = None,
                     model_min_score: float | None = None) -> InferenceOptions:
        """The defaults with ``values`` on top (each stage section read over its defaults);
        unknown keys refused.

        ``model_min_score``: the model's own threshold (recorded with its weights,
        :attr:`dope_hope.model.info.ModelInfo.min_score`); it replaces the default
        ``min_score`` unless ``values`` gives one.
        """
        values = dict(values or {})
        if model_min_score is not None and "min_score" not in values:
            values["min_score"] = model_min_score
        return super().from_mapping(values)
