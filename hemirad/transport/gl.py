"""The one OpenGL context of the process (headless EGL), made on first use."""
from __future__ import annotations

import importlib.util
import os
import threading
from typing import Callable

import moderngl

from hemirad.core.errors import HemiradInputError


class GLContext:
    """Owns the process's moderngl context.

    The context is made once, on first use. ``get(gpu=True)`` makes it on a hardware EGL
    device (the NVIDIA one beside CUDA) instead of the first device EGL lists, and refuses
    when the process already holds a software context: GL objects cannot move between
    contexts, so ask for the GPU before anything else draws.

    GL calls from a thread other than the creating one silently do nothing with EGL, so
    ``get`` refuses them loudly instead.
    """

    _instance: "GLContext | None" = None

    def __init__(self, gpu: bool = False):
        _load_triton_first()
        _share_cores_with_the_rasteriser()
        _draw_on_a_driver_thread()
        try:
            self.ctx = _hardware_context() if gpu else _context(device_index=None)
        except HemiradInputError:
            raise
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
    def get(cls, gpu: bool = False) -> moderngl.Context:
        if cls._instance is None:
            cls._instance = cls(gpu)
        if threading.get_ident() != cls._instance.thread:
            raise RuntimeError("OpenGL is used from a thread other than the one that made the context")
        if gpu and _is_software(cls._instance.renderer):
            raise HemiradInputError(
                f"a GPU OpenGL context was asked for, but this process already renders with "
                f"{cls._instance.renderer}; solve on the GPU before anything else in the process uses OpenGL.")
        return cls._instance.ctx

    @classmethod
    def renderer_name(cls) -> str:
        cls.get()
        return cls._instance.renderer

    @classmethod
    def is_software(cls) -> bool:
        """Whether the renderer runs on the CPU (Mesa's llvmpipe or softpipe)."""
        return _is_software(cls.renderer_name())

    @classmethod
    def max_image_size(cls, gpu: bool = False) -> int:
        """The longest side, in pixels, of an image the context's framebuffers hold
        (GL_MAX_RENDERBUFFER_SIZE). ``gpu`` as for ``get``."""
        return int(cls.get(gpu).info.get("GL_MAX_RENDERBUFFER_SIZE", 4096))


    @classmethod
    def framebuffer_fits(cls, width: int, height: int, gpu: bool = False) -> bool:
        """Whether a float RGBA framebuffer with a depth buffer, ``width`` x ``height``, can be
        made here: a side within the limit is not enough (Mesa's llvmpipe refuses one of
        12288 x 12288 though its limit is 16384). Made and released, to know for sure."""
        ctx = cls.get(gpu)
        made = []
        try:
            made.append(ctx.renderbuffer((width, height), components=4, dtype="f4"))
            made.append(ctx.depth_renderbuffer((width, height)))
            made.append(ctx.framebuffer(color_attachments=[made[0]], depth_attachment=made[1]))
            return True
        except Exception:  # moderngl.Error (incomplete, out of memory) and the like
            return False
        finally:
            for resource in reversed(made):
                resource.release()


def check_image_size(side: int, refusal: Callable[[int], Exception], gpu: bool = False) -> None:
    """Raise ``refusal(limit)`` when an image ``side`` pixels long exceeds what OpenGL's
    framebuffers hold here (``limit``, ``GLContext.max_image_size``)."""
    limit = GLContext.max_image_size(gpu)
    if side > limit:
        raise refusal(limit)


def _is_software(renderer: str) -> bool:
    return any(name in renderer.lower() for name in ("llvmpipe", "softpipe", "software"))


def _context(device_index: int | None) -> moderngl.Context:
    settings = {} if device_index is None else {"device_index": device_index}
    return moderngl.create_standalone_context(backend="egl", require=330, **settings)


def _hardware_context(max_devices: int = 16) -> moderngl.Context:
    """A context on the first EGL device whose renderer is not a software one.

    EGL lists every vendor's devices (with glvnd, NVIDIA's and Mesa's side by side, in an
    order that depends on the machine), so each is opened in turn until one is hardware.
    """
    if os.environ.get("GLCONTEXT_DEVICE_INDEX"):  # the user chose; glcontext honours it
        return _context(None)
    seen = []
    for index in range(max_devices):
        try:
            ctx = _context(index)
        except Exception as exc:  # past the last device, or one that cannot make a context
            if "requested device index" in str(exc):
                break
            seen.append(f"device {index}: {exc}")
            continue
        renderer = ctx.info.get("GL_RENDERER", "unknown")
        if not _is_software(renderer):
            return ctx
        seen.append(f"device {index}: {renderer}")
        ctx.release()
    raise HemiradInputError(
        "a GPU was asked for, but no EGL device renders in hardware (" + ("; ".join(seen) or "none found") +
        "). Install the NVIDIA driver's EGL library (libEGL_nvidia, with its glvnd vendor file), "
        "or solve with --device cpu.")


def _share_cores_with_the_rasteriser() -> None:
    """Leave llvmpipe one core fewer than the process may use (``LP_NUM_THREADS``, read when
    the context is made; a value the user set stays): a sweep keeps two threads of its own
    busy beside the rasteriser (drawing, and making the previous group's light), and on two
    cores a second raster thread only took turns with them. Measured on the furnished room
    (2 cores, five interleaved pairs): 11.7-12.2 s against 12.3-13.7 s with llvmpipe's two;
    the paper's configuration, with no worker, the same (the fingerprints' ten runs 29.0 s
    against 28.7 s)."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ.setdefault("LP_NUM_THREADS", str(max(1, cores - 1)))


def _draw_on_a_driver_thread() -> None:
    """Let Mesa run the GL calls on a thread of its own (glthread, the ``mesa_glthread``
    option, read when the context is made; a value the user set stays): a draw call then
    returns at once, and llvmpipe's vertex stage and binning, about 1.2 ms of a 6,000-triangle
    hemicube, run there while this thread decodes the hemicube before. The atlases are the
    same; only reads (glReadPixels, glFinish) wait. Measured on the furnished room (2 cores):
    the drawing thread's CPU in its 1,328-hemicube sweep 4.7 -> 3.1 s, the solve 10.6 and
    11.2 s -> 9.9 and 10.0 s interleaved. Mesa says on stderr that an option came from the
    environment unless ``MESA_DEBUG`` is silent, which it is made when this sets the option."""
    if "mesa_glthread" not in os.environ:
        os.environ["mesa_glthread"] = "true"
        os.environ.setdefault("MESA_DEBUG", "silent")


def _load_triton_first() -> None:
    """Import triton, when installed, before Mesa loads its own LLVM into the process.

    PyTorch's CUDA wheels bring triton, which links another LLVM. Imported after llvmpipe has
    loaded LLVM 15, triton's native module crashes the process (seen with torch 2.15 and Mesa
    22.3); imported before, both work. torch.func imports it lazily (through torch._dynamo)
    on its first transform (jacfwd), which may come after the context is made.
    """
    if importlib.util.find_spec("triton") is not None:
        import triton  # noqa: F401
