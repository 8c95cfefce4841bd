"""Typed inference options: what a :class:`~dope_hope.inference.predictor.DopePredictor` does
with a model's maps. The defaults live in the packaged ``dope_hope/configs/infer.yaml``;
every key, top level and per stage, is checked (an unknown key or a bad value is a
ConfigError). Each stage's section is checked by that stage's settings dataclass, which sits
beside the stage's function and owns the defaults (:class:`StageSettings`).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

from dope_hope.errors import ConfigError

if TYPE_CHECKING:
    from dope_hope.config import SectionSettings
    from dope_hope.inference.pnp import PnpSettings
    from dope_hope.inference.pose_search import HypothesisSettings
    from dope_hope.inference.tracking_settings import TrackingSettings
    from dope_hope.maps.decode import DecodeSettings
    from dope_hope.refine.icp import IcpSettings
    from dope_hope.refine.line_search import LineSearchSettings

#: Pose searches: multi-hypothesis PnP over corner candidates, or DOPE's one-to-one grouping.
POSE_SEARCHES = ("hypotheses", "groups")


def _stage_settings() -> dict[str, type[SectionSettings]]:
    """Section name -> the settings dataclass that checks it (its fields are the section's keys)."""
    from dope_hope.inference.pnp import PnpSettings
    from dope_hope.inference.pose_search import HypothesisSettings
    from dope_hope.inference.tracking_settings import TrackingSettings
    from dope_hope.maps.decode import DecodeSettings
    from dope_hope.refine.icp import IcpSettings
    from dope_hope.refine.line_search import LineSearchSettings

    return {"decode": DecodeSettings, "pnp": PnpSettings, "hypotheses": HypothesisSettings,
            "line_search": LineSearchSettings, "icp_refine": IcpSettings, "tracking": TrackingSettings}


@dataclass(frozen=True)
class StageSettings:
    """The stage sections of :class:`InferenceOptions` as their settings objects: decode
    (:func:`~dope_hope.maps.decode.corner_candidates` / :func:`~dope_hope.maps.decode.decode_maps`),
    pnp (:func:`~dope_hope.inference.pnp.solve_pnp`), hypotheses
    (:func:`~dope_hope.inference.pose_search.solve_pnp_candidates`), line_search
    (:func:`~dope_hope.refine.line_search.depth_line_search`), icp_refine
    (:func:`~dope_hope.refine.icp.icp_refine`), tracking (the stream tracker)."""

    decode: DecodeSettings
    pnp: PnpSettings
    hypotheses: HypothesisSettings
    line_search: LineSearchSettings
    icp_refine: IcpSettings
    tracking: TrackingSettings


@dataclass(frozen=True)
class InferenceOptions:
    """Inference options (see ``dope_hope/configs/infer.yaml`` for each key's meaning).

    height: working height in px or None (the model's training scale). pose_search: one of
    :data:`POSE_SEARCHES`. min_score: detections below are dropped. ls_points / icp_points:
    model points for -LS / ICP. icp: ICP after -LS when depth is given. decode, pnp,
    hypotheses, line_search, icp_refine, tracking: each stage's section, a mapping of its
    settings over their defaults; :attr:`stages` holds them as the settings objects the
    stages take (checked here, names and values).
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
        stages = {}
        for section, settings in _stage_settings().items():
            value = getattr(self, section)
            if not isinstance(value, Mapping):
                raise ConfigError(f"{section} must be a mapping of settings, got {value!r}")
            stages[section] = settings.from_mapping(value)  # values checked as well as names
        object.__setattr__(self, "_stages", StageSettings(**stages))
        object.__setattr__(self, "height", None if h is None else int(h))
        object.__setattr__(self, "min_score", min_score)
        for name, value in points.items():
            object.__setattr__(self, name, value)

    @property
    def stages(self) -> StageSettings:
        """The stage sections as the settings objects their functions take."""
        return self._stages

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
