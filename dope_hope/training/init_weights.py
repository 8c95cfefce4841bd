"""The weights a new run starts from (``--init``): a dope-hope checkpoint's network copied into
the run's, widened to more objects, wider stages or more stages where the run's architecture
asks for them (the start then computes the same maps)."""
from __future__ import annotations

import logging
from pathlib import Path

import torch
from torch import nn

from dope_hope.errors import ModelFileError
from dope_hope.model.checkpoint import check_state_dict, load_checkpoint
from dope_hope.model.lite import deepen_stages, stage_channels_of, stage_count_of, widen_stage_channels
from dope_hope.model.network import num_objects_of, widen_to_objects

#: The trainer's logger: these lines are the trainer's, under its name.
log = logging.getLogger("dope_hope.training.trainer")


def load_init_weights(model: nn.Module, path: str | Path) -> None:
    """Copy a dope-hope checkpoint's network weights into ``model`` (``--init``); a one-object
    start of a model of N > 1 objects is widened first (every group a copy of its one group:
    :func:`dope_hope.model.network.widen_to_objects`), and a lite start's stages to a wider
    ``model.lite.stage_channels`` (:func:`dope_hope.model.lite.widen_stage_channels`): the
    network starts computing the start's maps either way; and to more ``model.stages``
    (:func:`dope_hope.model.lite.deepen_stages`: the start's last stage applied again).

    Raises ModelFileError naming the file when it is no checkpoint, was trained with another
    architecture than ``model`` (compare the configs' ``model`` sections) or holds weights
    that are not finite (NaN / inf: every step from them would be NaN).
    """
    ck = load_checkpoint(path)
    state = ck["model"]
    n = int(getattr(model, "num_objects", 1))
    widen = n > 1 and num_objects_of(ck["config"]) == 1
    if widen:
        state = widen_to_objects(state, ck["config"], n)
    own = model.state_dict()
    start_width, width = stage_channels_of(state), stage_channels_of(own)
    wider = start_width is not None and width is not None and width > start_width
    if wider:
        state = widen_stage_channels(state, width)
    start_depth, depth = stage_count_of(state), stage_count_of(own)
    deeper = start_depth >= 2 and depth > start_depth
    if deeper:
        state = deepen_stages(state, depth)
    check_state_dict(own, state, path)
    bad = [k for k, v in state.items()
           if isinstance(v, torch.Tensor) and v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if bad:
        raise ModelFileError(path, f"{len(bad)} weight tensor(s) hold NaN or inf values (e.g. {bad[0]}); "
                                   "a run cannot start from them")
    model.load_state_dict(state, strict=True)
    how = [f"its one object widened to {n}"] if widen else []
    how += [f"its stages widened from {start_width} to {width} channels"] if wider else []
    how += [f"its {start_depth} stages deepened to {depth}, each new one a copy of the last"] if deeper else []
    log.info("initialised the network from %s%s", path, f" ({'; '.join(how)})" if how else "")
