"""Torch device names: checked once, with a one-line error, before a model or data is loaded."""
from __future__ import annotations

from dope_hope.errors import ConfigError


def check_device(name: str, allow_auto: bool = True) -> str:
    """``name`` if this machine has that torch device: "auto" (CUDA when available, else CPU),
    "cpu", "cuda", "cuda:<i>", or another torch device type that is available.

    Raises:
        ConfigError: a malformed name, or a CUDA device this machine lacks.
    """
    text = str(name).strip()
    if text == "cpu" or (allow_auto and text == "auto"):
        return text
    import torch

    try:
        dev = torch.device(text)
    except (RuntimeError, ValueError):
        raise ConfigError(f"{text!r}: not a torch device (cpu, cuda, cuda:1"
                          + (", auto" if allow_auto else "") + ")") from None
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigError(f"{text!r}: no CUDA device available")
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ConfigError(f"{text!r}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif dev.type != "cpu":
        backend = getattr(torch.backends, dev.type, None)
        available = getattr(backend, "is_available", None)
        if available is None or not available():
            raise ConfigError(f"{text!r}: not available on this machine")
    return text
