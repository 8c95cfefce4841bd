"""Training loss and one optimizer step.

Per stage, ``belief_weight * MSE(belief) + affinity_weight * MSE(affinity)`` (optionally
foreground-weighted), summed over stages (DOPE's deep supervision).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


# =============================================================================== helpers
def stage_loss(outputs: list[tuple[torch.Tensor, torch.Tensor]], belief: torch.Tensor,
               affinity: torch.Tensor, belief_weight: float = 1.0, affinity_weight: float = 1.0,
               foreground_weight: float = 0.0) -> torch.Tensor:
    """Sum over stages of ``belief_weight * MSE(belief) + affinity_weight * MSE(affinity)``, in
    float32.

    ``foreground_weight`` f > 0 weights each belief cell by ``1 + f * target`` and each affinity
    cell inside a corner's disk by ``1 + f``: the Gaussian peaks cover ~1 % of the cells, so a
    plain MSE is dominated by the zero background and learns the peaks (and which corner is
    which) slowly. f = 0 is the official plain MSE.
    """
    total = belief.new_zeros(())
    if foreground_weight:
        wb = 1.0 + foreground_weight * belief
        wa = 1.0 + foreground_weight * (affinity != 0).to(affinity.dtype)
    for b, a in outputs:
        if foreground_weight:
            lb = (wb * (b.float() - belief).square()).mean()
            la = (wa * (a.float() - affinity).square()).mean()
        else:
            lb, la = F.mse_loss(b.float(), belief), F.mse_loss(a.float(), affinity)
        total = total + belief_weight * lb + affinity_weight * la
    return total


def optimizer_step(model: nn.Module, optimizer: torch.optim.Optimizer, images: torch.Tensor, belief: torch.Tensor,
                   affinity: torch.Tensor, amp: bool = False, belief_weight: float = 1.0,
                   affinity_weight: float = 1.0, grad_clip: float | None = None,
                   foreground_weight: float = 0.0) -> float:
    """One training step: forward (bf16 autocast on the images' device when ``amp``; the trainer
    sets it only where the device computes bf16 natively), per-stage loss in float32, backward,
    optional global grad-norm clipping, optimizer step. Returns the loss."""
    model.train()
    with torch.autocast(images.device.type, dtype=torch.bfloat16, enabled=amp):
        outputs = model(images)
    loss = stage_loss(outputs, belief, affinity, belief_weight, affinity_weight, foreground_weight)
    optimizer.zero_grad(set_to_none=True)
    loss.backward()
    if grad_clip:
        torch.nn.utils.clip_grad_norm_(model.parameters(), float(grad_clip))
    optimizer.step()
    return float(loss.detach())
