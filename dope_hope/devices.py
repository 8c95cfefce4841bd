"""Torch device names: checked once, with a one-line error, before a model or data is loaded."""
from __future__ import annotations

import os
from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path

from dope_hope.errors import ConfigError

#: /proc/cpuinfo flags of x86 CPUs that compute bfloat16 in hardware (oneDNN's AMX and
#: AVX512-BF16 kernels); elsewhere bf16 autocast on the CPU is emulated and slower than fp32.
_CPU_BF16_FLAGS = ("amx_bf16", "avx512_bf16")

#: oneDNN ISA caps (``ONEDNN_MAX_CPU_ISA``, older ``DNNL_MAX_CPU_ISA``) that keep its kernels
#: off every bf16 instruction: under them bf16 autocast is emulated whatever the CPU has (with
#: ``AVX2`` on an AMX Xeon, 20 lite steps took over 120 s against 6 s in float32).
_ONEDNN_CAPS_WITHOUT_BF16 = ("SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE",
                             "AVX512_CORE_VNNI")


def onednn_cap(environ: Mapping[str, str] | None = None) -> str | None:
    """The oneDNN ISA cap set in the environment (upper case), or None."""
    env = os.environ if environ is None else environ
    value = env.get("ONEDNN_MAX_CPU_ISA") or env.get("DNNL_MAX_CPU_ISA")
    return value.strip().upper() if value and value.strip() else None


def onednn_cap_allows_bf16(environ: Mapping[str, str] | None = None) -> bool:
    """False where the environment caps oneDNN below its bf16 kernels (:data:`_ONEDNN_CAPS_WITHOUT_BF16`)."""
    return onednn_cap(environ) not in _ONEDNN_CAPS_WITHOUT_BF16


def check_device(name: str, allow_auto: bool = True) -> str:
    """``name`` if this machine has that torch device: "auto" (CUDA when available, else CPU),
    "cpu", "cuda", "cuda:<i>", or another torch device type that is available.

    Raises:
        ConfigError: a malformed name, or a CUDA device this machine lacks.
    """
    text = str(name).strip()
    if text == "cpu" or (allow_auto and text == "auto"):
        return text
    import torch  # noqa: PLC0415 (torch only to check a device (the CPU description needs none))

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


@lru_cache(maxsize=None)
def cpu_has_native_bf16(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool:
    """Whether ``cpuinfo``'s first ``flags`` line names AMX-BF16 or AVX512-BF16 (False where
    the file is missing: not Linux)."""
    try:
        text = cpuinfo.read_text(encoding="utf-8", errors="replace")
    except OSError:
        return False
    flags = next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), [])
    return any(flag in flags for flag in _CPU_BF16_FLAGS)


#: /proc/cpuinfo flags that decide how fast (and in which precision) the CPU trains and infers:
#: AMX (bf16 tiles), AVX-512 BF16, VNNI (int8 dot products), and the vector widths below them.
CPU_PRECISION_FLAGS = ("amx_bf16", "amx_int8", "avx512_bf16", "avx512_vnni", "avx_vnni", "avx512f", "avx2")


def cpu_description(cpuinfo: Path = Path("/proc/cpuinfo")) -> dict[str, object]:
    """The CPU's ``model`` name, its ``flags`` among :data:`CPU_PRECISION_FLAGS` (name ->
    present) and whether training's bf16 is native (``native_bf16``: the flags, unless the
    environment caps oneDNN below bf16), from ``cpuinfo``'s first processor (model "unknown"
    and no flags where the file is missing: not Linux)."""
    try:
        text = cpuinfo.read_text(encoding="utf-8", errors="replace")
    except OSError:
        text = ""
    lines = text.splitlines()
    model = next((ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("model name")), "unknown")
    flags = set(next((ln.split(":", 1)[1].split() for ln in lines if ln.startswith("flags")), []))
    return {"model": model, "flags": {f: f in flags for f in CPU_PRECISION_FLAGS},
            "native_bf16": any(f in flags for f in _CPU_BF16_FLAGS) and onednn_cap_allows_bf16()}


def cpu_line(cpuinfo: Path = Path("/proc/cpuinfo")) -> str:
    """One line for a benchmark's header: the CPU model and which precision flags it has."""
    d = cpu_description(cpuinfo)
    has = [f for f, v in d["flags"].items() if v]
    lacks = [f for f, v in d["flags"].items() if not v]
    cap = onednn_cap()
    return (f"CPU {d['model']}: {', '.join(has) or 'none'} of the precision flags"
            + (f" (no {', '.join(lacks)})" if lacks else "")
            + (f"; ONEDNN_MAX_CPU_ISA={cap}" if cap else "")
            + f"; bf16 training {'native' if d['native_bf16'] else 'emulated: float32 used'}")


def native_bf16(device_type: str) -> bool:
    """Whether bf16 autocast is a speed-up on this machine's ``device_type`` ("cuda", "cpu"):
    a CUDA device with bf16 support, or an x86 CPU with AMX-BF16 / AVX512-BF16 (Linux) whose
    oneDNN the environment does not cap below them (``ONEDNN_MAX_CPU_ISA=AVX2``: float32)."""
    if device_type == "cuda":
        import torch  # noqa: PLC0415 (torch only to check a device (the CPU description needs none))

        return bool(torch.cuda.is_available() and torch.cuda.is_bf16_supported())
    return device_type == "cpu" and cpu_has_native_bf16() and onednn_cap_allows_bf16()
