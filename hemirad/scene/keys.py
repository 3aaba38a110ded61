"""Checked reading of nested YAML data: each value's type and range, the keys a mapping may
have, and a did-you-mean hint for a misspelt name.

Every check raises :class:`SceneError` naming the document, the key path of the value
(``objects[3].material``), what was expected and what was found.
"""
from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Iterable, Mapping

from hemirad.core.errors import SceneError


def join(path: str, key: object) -> str:
    """The key path of ``key`` inside ``path``: ``camera`` + ``fov`` is ``camera.fov``."""
    return f"{path}.{key}" if path else str(key)


def is_number(v: object) -> bool:
    # YAML's true/false arrive as bool, a subclass of int: they are not numbers here.
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def is_finite(v: int | float) -> bool:
    """Finite as a float: YAML integers have no size limit, and past 1e308 none converts."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


#: Coordinates (and other lengths) beyond this are refused: OpenGL draws in 32-bit floats, and
#: differences of larger numbers lose every digit a scene's detail needs.
MAX_COORDINATE = 1e15


def closest(value: object, options: Iterable[str]) -> str | None:
    """The option ``value`` most likely misspells, or None when none is close (or it is no
    short string: a name is never a number, a list or a paragraph)."""
    if not isinstance(value, str) or len(value) > 100:
        return None
    close = difflib.get_close_matches(value, list(options), n=1)
    return close[0] if close else None


def did_you_mean(value: object, options: Iterable[str]) -> str:
    """``"Did you mean 'pattern2'?"`` for a near miss, else ``""``."""
    close = closest(value, options)
    return f"Did you mean '{close}'?" if close is not None else ""


def _bool_hint(v: object) -> str:
    return "true/false is not a number." if isinstance(v, bool) else ""


class Checker:
    """Reads values out of one document; every method takes the key path of what it reads.

    Args:
        file: how to name the document in error messages.
        required_what: what a missing required key should hold, by key name, for the message.
    """

    def __init__(self, file: str, required_what: Mapping[str, str] | None = None):
        self.file, self.required_what = file, required_what or {}

    def fail(self, key: str, expected: str, got: object = ..., hint: str = ""):
        raise SceneError(self.file, key, expected, got, hint)

    def mapping(self, v, key: str, expected: str) -> dict:
        if not isinstance(v, dict):
            self.fail(key, expected, v)
        return v

    def keys(self, m: dict, key: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()):
        """Refuse a key of ``m`` not in ``allowed``, and a missing one of ``required``."""
        for k in m:
            if not isinstance(k, str) or k not in allowed:
                self.fail(join(key, k), f"one of the keys {', '.join(allowed)}", k, did_you_mean(k, allowed))
        for k in required:
            if k not in m:
                self.fail(join(key, k), self.required_what.get(k, "a value"), hint="The key is missing.")

    def section(self, v, key: str, expected: str, allowed: tuple[str, ...], required: tuple[str, ...] = ()) -> dict:
        """A mapping with only ``allowed`` keys, ``required`` among them."""
        m = self.mapping(v, key, expected)
        self.keys(m, key, allowed, required)
        return m

    def number(self, v, key: str, expected: str) -> float:
        if not is_number(v):
            self.fail(key, expected, v, _bool_hint(v))
        if not is_finite(v):
            self.fail(key, expected, v, "The number must be finite (and below about 1e308).")
        return float(v)

    def bounded(self, v, key: str, expected: str, ok: Callable[[float], bool]) -> float:
        """A finite number for which ``ok`` holds."""
        x = self.number(v, key, expected)
        if not ok(x):
            self.fail(key, expected, v)
        return x

    def integer(self, v, key: str, expected: str, lo: int, hi: int | None = None) -> int:
        if not isinstance(v, int) or isinstance(v, bool) or v < lo or (hi is not None and v > hi):
            self.fail(key, expected, v, _bool_hint(v))
        return int(v)

    def point(self, v, key: str, expected: str = "three numbers [x, y, z]") -> tuple[float, float, float]:
        """A position: three numbers, none larger in size than ``MAX_COORDINATE``."""
        p = self.vec3(v, key, expected)
        for i, x in enumerate(p):
            if abs(x) > MAX_COORDINATE:
                self.fail(f"{key}[{i}]", f"a coordinate within +-{MAX_COORDINATE:g}", x,
                          "OpenGL draws in 32-bit floats; move the scene nearer the origin or use larger units.")
        return p

    def vec3(self, v, key: str, expected: str = "three numbers [x, y, z]") -> tuple[float, float, float]:
        if not isinstance(v, (list, tuple)) or len(v) != 3:
            self.fail(key, expected, v)
        for i, x in enumerate(v):
            self.number(x, f"{key}[{i}]", "a finite number")
        return tuple(float(x) for x in v)

    def rgb(self, v, key: str, expected: str, ok) -> tuple[float, float, float]:
        """One number (grey) or three; ``ok(x)`` says whether a channel value is allowed."""
        if is_number(v):
            v = [v, v, v]
        if not isinstance(v, (list, tuple)) or len(v) != 3 or not all(is_number(x) for x in v):
            self.fail(key, expected, v, _bool_hint(v))
        if not all(is_finite(x) and ok(x) for x in v):
            self.fail(key, expected, v)
        return tuple(float(x) for x in v)

    def boolean(self, v, key: str) -> bool:
        if not isinstance(v, bool):
            self.fail(key, "true or false", v)
        return v

    def choice(self, v, key: str, options: tuple[str, ...]) -> str:
        if not isinstance(v, str) or v not in options:
            self.fail(key, f"one of {', '.join(options)}", v, did_you_mean(v, options))
        return v
