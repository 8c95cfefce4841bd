"""Typed inference options: what a :class:`~dope_hope.inference.predictor.DopePredictor` does
with a model's maps. The defaults live in the packaged ``dope_hope/configs/infer.yaml``;
every key, top level and per stage, is checked (an unknown key is a ConfigError).
"""
from __future__ import annotations

import inspect
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, fields
from typing import Any

from dope_hope.errors import ConfigError

#: Pose searches: multi-hypothesis PnP over corner candidates, or DOPE's one-to-one grouping.
POSE_SEARCHES = ("hypotheses", "groups")


def _stage_functions() -> dict[str, list[Callable[..., Any]]]:
    """Section name -> the functions whose keyword arguments the section may hold."""
    from dope_hope.inference.pnp import solve_pnp, solve_pnp_candidates
    from dope_hope.inference.tracking_settings import TrackingSettings
    from dope_hope.maps.decode import corner_candidates, decode_maps
    from dope_hope.refine.icp import icp_refine
    from dope_hope.refine.line_search import depth_line_search

    return {"decode": [corner_candidates, decode_maps], "pnp": [solve_pnp],
            "hypotheses": [solve_pnp_candidates], "line_search": [depth_line_search],
            "icp_refine": [icp_refine], "tracking": [TrackingSettings]}


#: Arguments the predictor passes itself (maps, points, camera, depth, the pose search's
#: consensus pose): not options.
_PASSED_BY_PREDICTOR = {"belief", "affinity", "stride", "keypoints", "scores", "keypoint_ids", "xy",
                        "cuboid", "cuboid_3d", "K", "R", "t", "model_points", "model_normals", "depth",
                        "dist_coeffs", "initial_pose", "peaks"}


def _stage_keywords(functions: list[Callable[..., Any]]) -> set[str]:
    names: set[str] = set()
    for fn in functions:
        for p in inspect.signature(fn).parameters.values():
            if p.default is not inspect.Parameter.empty and p.name not in _PASSED_BY_PREDICTOR:
                names.add(p.name)
    return names


@dataclass(frozen=True)
class InferenceOptions:
    """Inference options (see ``dope_hope/configs/infer.yaml`` for each key's meaning).

    height: working height in px or None (the model's training scale). pose_search: one of
    :data:`POSE_SEARCHES`. min_score: detections below are dropped. ls_points / icp_points:
    model points for -LS / ICP. icp: ICP after -LS when depth is given. decode, pnp,
    hypotheses, line_search, icp_refine: keyword arguments of each stage's function.
    tracking: settings of the stream tracker
    (:class:`~dope_hope.inference.tracking.TrackingSettings`, checked here).
    """

    height: int | None
    pose_search: str
    min_score: float
    ls_points: int
    icp: bool
    icp_points: int
    decode: Mapping[str, Any]
    pnp: Mapping[str, Any]
    hypotheses: Mapping[str, Any]
    line_search: Mapping[str, Any]
    icp_refine: Mapping[str, Any]
    tracking: Mapping[str, Any]

    def __post_init__(self) -> None:
        from dope_hope.config import finite_float, whole_number
        from dope_hope.preprocess import check_working_side

        h = self.height
        if h is not None:
            check_working_side(h)
        if self.pose_search not in POSE_SEARCHES:
            raise ConfigError(f"pose_search must be one of {', '.join(POSE_SEARCHES)}, got {self.pose_search!r}")
        min_score = finite_float(self.min_score, "min_score")
        points = {name: whole_number(getattr(self, name), name, 10) for name in ("ls_points", "icp_points")}
        if not isinstance(self.icp, bool):
            raise ConfigError(f"icp must be true or false, got {self.icp!r}")
        for section, functions in _stage_functions().items():
            value = getattr(self, section)
            if not isinstance(value, Mapping):
                raise ConfigError(f"{section} must be a mapping of keyword arguments, got {value!r}")
            allowed = _stage_keywords(functions)
            unknown = sorted(set(value) - allowed)
            if unknown:
                raise ConfigError(f"unknown {section} option(s) {', '.join(unknown)}; known: "
                                  f"{', '.join(sorted(allowed))}")
        from dope_hope.inference.tracking_settings import TrackingSettings

        TrackingSettings.from_mapping(self.tracking)  # values checked as well as names
        object.__setattr__(self, "height", None if h is None else int(h))
        object.__setattr__(self, "min_score", min_score)
        for name, value in points.items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_mapping(cls, overrides: Mapping[str, Any] | None = None, base: str = "infer",
                     model_min_score: float | None = None) -> InferenceOptions:
        """The packaged defaults (config ``base``) with ``overrides`` on top; unknown keys refused.

        ``model_min_score``: the model's own threshold (recorded with its weights,
        :attr:`dope_hope.model.info.ModelInfo.min_score`); it replaces the packaged
        ``min_score`` unless ``overrides`` gives one.
        """
        from dope_hope.config import load_config

        values = dict(load_config(base))
        if model_min_score is not None:
            values["min_score"] = model_min_score
        for key, value in (overrides or {}).items():
            if key not in values:
                raise ConfigError(f"unknown inference option {key!r}; known: {', '.join(sorted(values))}")
            values[key] = value
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - names)
        if unknown:
            raise ConfigError(f"unknown inference option(s) {', '.join(unknown)}")
        missing = sorted(names - set(values))
        if missing:
            raise ConfigError(f"inference config lacks {', '.join(missing)}")
        return cls(**values)

    def to_dict(self) -> dict[str, Any]:
        return {k: (dict(v) if isinstance(v, Mapping) else v) for k, v in asdict(self).items()}
