"""The settings of `dope-hope adapt` (:class:`AdaptConfig`): how a label is confirmed by the
depth (``labels``), how far a confirmed pose is carried by the tracker (``carry``), how the
model is fine-tuned on the labels (``finetune``) and the inference options of the labelling
(``infer``: those of `dope-hope infer`, with ICP and three working sizes on by default).

``dope-hope settings adapt`` prints them all; ``--set section.key=value`` changes one.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from dope_hope.config import (
    SectionSettings,
    at_least,
    boolean,
    each,
    finite_float,
    fraction,
    nonnegative_float,
    or_none,
    positive_float,
    section,
)
from dope_hope.inference.options import InferenceOptions
from dope_hope.inference.scales import MultiscaleSettings

#: The working sizes the labelling runs by default (a far or near object found at one of them).
ADAPT_SCALES: tuple[float, ...] = (1.0, 0.75, 1.33)


@dataclass(frozen=True)
class LabelSettings(SectionSettings):
    """When the depth confirms a pose (:func:`dope_hope.adaptation.evidence.pose_evidence`).

    min_score: least detection score of a label (a carried label: its track's last score).
    min_measured: least share of the pose's visible, unoccluded surface where the sensor
    measured a depth. min_support: least share of those measured points whose depth confirms
    the surface within ``tolerance_m``. max_residual_m: largest median |depth - surface| over
    those points, metres. min_edge: least share of the pose's silhouette outline that lies
    on a depth edge within ``edge_px``. edge_jump: relative depth jump that makes an edge.
    tolerance_m: depth agreement of a supported point, metres. min_points: fewest visible
    unoccluded surface points (of the predictor's ls_points samples) a label needs (smaller: too little evidence).
    """

    SECTION = "labels"
    RULES = {"min_score": finite_float, "min_measured": fraction, "min_support": fraction,
             "max_residual_m": positive_float,
             "min_edge": fraction, "edge_px": at_least(0), "edge_jump": positive_float,
             "tolerance_m": positive_float, "min_points": at_least(1)}

    min_score: float = 0.3
    min_measured: float = 0.3
    min_support: float = 0.8
    max_residual_m: float = 0.006
    min_edge: float = 0.5
    edge_px: int = 3
    edge_jump: float = 0.03
    tolerance_m: float = 0.01
    min_points: int = 30


@dataclass(frozen=True)
class CarrySettings(SectionSettings):
    """Labels carried by the tracker into frames where the model missed the object.

    enabled: carry at all. max_frames: farthest frame from a confirmed label, before or after
    it (the tracker's ``max_coast``). chain: a carried label the depth confirms is carried on
    in turn (the passes repeat until none is added), so a run of missed frames longer than
    ``max_frames`` is filled one depth-confirmed frame at a time. seed_scales: the working
    sizes the model runs at again, on the frames of a sequence where it confirmed no detection
    (a far, small object is found at a larger size: one confirmed label there seeds the
    carrying of the whole sequence); null for none.
    """

    SECTION = "carry"
    RULES = {"enabled": boolean, "max_frames": at_least(1), "chain": boolean,
             "seed_scales": or_none(each(positive_float))}

    enabled: bool = True
    max_frames: int = 5
    chain: bool = True
    seed_scales: tuple[float, ...] | None = (1.77,)


@dataclass(frozen=True)
class FineTuneSettings(SectionSettings):
    """The fine-tuning of the model on its labels (`dope-hope train`'s entry point).

    rounds: label, train, label again, this many times. time_budget_min: minutes of training
    of all rounds together (shared evenly). synthetic_ratio: synthetic frames per labelled
    frame in each round's training data (0: the labels alone; 4: docs/commands/adapt.md says
    why). max_synthetic: most synthetic
    frames per round (None: no bound). lr: learning rate of the fine-tuning (None: the
    model's recipe's). steps: optimizer steps per round instead of the time budget (None:
    the budget decides). batch_size: frames per step (None: the recipe's, lowered to fit the
    round's frames). seed: the synthetic frames' draw and the run's.
    """

    SECTION = "finetune"
    RULES = {"rounds": at_least(1), "time_budget_min": positive_float, "synthetic_ratio": nonnegative_float,
             "max_synthetic": or_none(at_least(1)), "lr": or_none(positive_float), "steps": or_none(at_least(1)),
             "batch_size": or_none(at_least(1)), "seed": at_least(0)}

    rounds: int = 2
    time_budget_min: float = 10.0
    synthetic_ratio: float = 4.0
    max_synthetic: int | None = None
    lr: float | None = 3e-4
    steps: int | None = None
    batch_size: int | None = None
    seed: int = 0


@dataclass(frozen=True)
class AdaptMultiscale(MultiscaleSettings):
    """The labelling's working sizes: :class:`MultiscaleSettings` with three by default."""

    SECTION = "infer.multiscale"
    scales: tuple[float, ...] = ADAPT_SCALES


@dataclass(frozen=True)
class AdaptInferenceOptions(InferenceOptions):
    """The labelling's inference options: `dope-hope infer`'s, with ICP and three working sizes
    by default."""

    SECTION = "infer"
    icp: bool = True
    multiscale: AdaptMultiscale = section(AdaptMultiscale)

    def given(self) -> dict[str, Any]:
        """The options that differ from `dope-hope infer`'s defaults (top-level keys, whole
        sections): what the predictor is given, so a model's own score threshold still holds
        unless ``infer.min_score`` is set."""
        base = InferenceOptions().to_dict()
        return {k: v for k, v in self.to_dict().items() if v != base[k]}


@dataclass(frozen=True)
class AdaptConfig(SectionSettings):
    """Every setting of `dope-hope adapt`: labels, carry, finetune, infer (module docstring)."""

    SECTION = ""

    labels: LabelSettings = section(LabelSettings)
    carry: CarrySettings = section(CarrySettings)
    finetune: FineTuneSettings = section(FineTuneSettings)
    infer: AdaptInferenceOptions = section(AdaptInferenceOptions)
