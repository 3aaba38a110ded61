"""The one OpenGL context of the process (headless EGL), made on first use."""
from __future__ import annotations

import importlib.util
import threading

import moderngl

from .errors import HemiradInputError


class GLContext:
    """Owns the process's moderngl context.

    GL calls from a thread other than the creating one silently do nothing with EGL, so
    ``get`` refuses them loudly instead.
    """

    _instance: "GLContext | None" = None

    def __init__(self):
        _load_triton_first()
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl", require=330)
        except Exception as exc:  # the cause is nearly always missing system packages
            raise HemiradInputError(
                "could not create a headless OpenGL context through EGL "
                f"({exc}). Install Mesa's EGL and software renderer with "
                "scripts/install_system_deps.sh (Debian/Ubuntu packages libegl1, "
                "libegl-mesa0, libgl1-mesa-dri, libgl1)."
            ) from exc
        self.thread = threading.get_ident()
        self.renderer = self.ctx.info.get("GL_RENDERER", "unknown")

    @classmethod
    def get(cls) -> moderngl.Context:
        if cls._instance is None:
            cls._instance = cls()
        if threading.get_ident() != cls._instance.thread:
            raise RuntimeError("OpenGL is used from a thread other than the one that made the context")
        return cls._instance.ctx

    @classmethod
    def renderer_name(cls) -> str:
        cls.get()
        return cls._instance.renderer

    @classmethod
    def is_software(cls) -> bool:
        """Whether the renderer runs on the CPU (Mesa's llvmpipe or softpipe)."""
        return any(name in cls.renderer_name().lower() for name in ("llvmpipe", "softpipe", "software"))


def _load_triton_first() -> None:
    """Import triton, when installed, before Mesa loads its own LLVM into the process.

    PyTorch's CUDA wheels bring triton, which links another LLVM. Imported after llvmpipe has
    loaded LLVM 15, triton's native module crashes the process (seen with torch 2.15 and Mesa
    22.3); imported before, both work. torch.func imports it lazily (through torch._dynamo)
    on the first forward-mode transform, which comes after the context is made.
    """
    if importlib.util.find_spec("triton") is not None:
        import triton  # noqa: F401
