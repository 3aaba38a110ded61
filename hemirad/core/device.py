"""Where a solve's tensor work runs: the CPU, or a CUDA device beside a GPU OpenGL context.

The names a scene (``solver.device``) or the command line (``--device``) may give are
``DEVICES``' keys, with what each means.
"""
from __future__ import annotations

import functools
import os
import re

import torch

from hemirad.core.errors import HemiradInputError

DEVICES = {
    "cpu": "the default: torch on the CPU, OpenGL on the first EGL device",
    "cuda": "torch on the current CUDA device, OpenGL on an NVIDIA EGL device",
    "cuda:N": "the same on CUDA device N",
    "auto": "cuda when PyTorch sees a CUDA device, else cpu",
}
DEVICE_NAMES = tuple(DEVICES)
# "N" in a name stands for a device number
_PATTERN = re.compile("^(?:" + "|".join(re.escape(n).replace("N", r"\d+") for n in DEVICE_NAMES) + ")$")


def is_device_name(name: str) -> bool:
    return isinstance(name, str) and bool(_PATTERN.match(name))


def select_device(name: str) -> torch.device:
    """The torch device ``name`` (one of ``DEVICE_NAMES``) stands for on this machine.

    Raises:
        HemiradInputError: a CUDA device is asked for and PyTorch sees none (or not that one).
    """
    if not is_device_name(name):
        raise HemiradInputError(f"unknown device {name!r}: expected one of {', '.join(DEVICE_NAMES)}.")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(name)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise HemiradInputError(
                f"device {name!r} was asked for, but PyTorch sees no CUDA device on this machine "
                f"(torch {torch.__version__}, CUDA build {torch.version.cuda or 'none'}). "
                "Use --device cpu (the default) or --device auto.")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise HemiradInputError(f"device {name!r} was asked for, but this machine has "
                                    f"{torch.cuda.device_count()} CUDA device(s), numbered from 0.")
        # cuBLAS sums in a fixed order only with this workspace setting, which must be made
        # before its first use; solves run in PyTorch's deterministic mode (runtime.py).
        os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    return device


def cached_per_device(build):
    """Cache the constant ``build(resolution)`` (tensors, or a tuple of them), made once on
    the CPU and copied once to each device it is asked for on.

    The wrapped function takes ``(resolution, device="cpu")``; callers pass the device of
    the tensors they combine it with. Do not modify what it returns.
    """
    @functools.lru_cache(maxsize=16)
    def cached(resolution: int, device: torch.device):
        if device.type == "cpu":
            with torch.device("cpu"):  # whatever the process's default device
                return build(resolution)
        made = cached(resolution, torch.device("cpu"))
        return tuple(t.to(device) for t in made) if isinstance(made, tuple) else made.to(device)

    @functools.wraps(build)
    def get(resolution: int, device: torch.device | str = "cpu"):
        return cached(resolution, torch.device(device))

    return get


def as_tensor(data, dtype: torch.dtype | None = None) -> torch.Tensor:
    """``torch.as_tensor`` that leaves a tensor on its own device: only data that is not a
    tensor yet (lists, NumPy arrays) is placed on the default device."""
    if isinstance(data, torch.Tensor):
        return data if dtype is None else data.to(dtype)
    return torch.as_tensor(data, dtype=dtype)
