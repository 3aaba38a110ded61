"""Pure tensor kernels compiled by TorchScript, so that they run without the interpreter lock.

A sweep makes its groups' light on a worker thread beside the thread that draws the
hemicubes (``transport.sweep``). Every eager torch operation lets go of the interpreter lock
and takes it back; two threads doing that in turn hand it to each other at every operation,
and a kernel of a hundred small operations then runs several times slower than alone. A
scripted kernel runs its whole graph with the lock released, in the same ATen operations
(torch's CPU fuser is off by default), so it gives the same numbers bit for bit.

``torch.jit.script`` is deprecated in favour of ``torch.compile``, which needs a C++
compiler at run time and fuses operations (other numbers in the last bits). Where scripting
is unavailable or fails, the kernel runs as the plain function: slower beside the worker,
the same numbers.
"""
from __future__ import annotations

import functools
import threading
import warnings
from typing import Callable, TypeVar

import torch

Kernel = TypeVar("Kernel", bound=Callable)

_lock = threading.Lock()


def scripted(function: Kernel) -> Kernel:
    """``function`` (a TorchScript-compatible function of tensors, annotated) compiled by
    TorchScript on its first call, or itself where that fails. ``.eager`` is the plain
    function and ``.is_scripted()`` says which runs. A call that autograd records (an input
    that requires grad) runs the plain function: a scripted graph's backward rounds
    otherwise in the last bits (1.6e-16 relative, seen on Lambert's factor)."""
    compiled: list[Callable] = []

    def kernel() -> Callable:
        if not compiled:
            with _lock:
                if not compiled:
                    compiled.append(_compile(function))
        return compiled[0]

    @functools.wraps(function)
    def run(*args):
        if torch.is_grad_enabled() and any(isinstance(a, torch.Tensor) and a.requires_grad for a in args):
            return function(*args)  # eager autograd: the gradients as before, bit for bit
        return kernel()(*args)

    run.eager = function
    run.is_scripted = lambda: kernel() is not function
    return run  # type: ignore[return-value]


def _compile(function: Callable) -> Callable:
    try:
        with warnings.catch_warnings():  # the deprecation notice (module docstring)
            warnings.simplefilter("ignore")
            return torch.jit.script(function)
    except Exception:  # noqa: BLE001 - any failure to compile leaves the plain function, same numbers
        return function
