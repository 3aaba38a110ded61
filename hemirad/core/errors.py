"""Errors a user can cause, reported as one paragraph and exit code 2 by the CLI."""
from __future__ import annotations

import reprlib

#: The longest message an input error prints; what a file or a library says is quoted in it.
MAX_MESSAGE = 2000


class _BoundedRepr(reprlib.Repr):
    """``repr`` that stops early: a few items of a container, a few levels deep, the ends
    of a long string, and an integer too long to print by its digit count. Its cost is
    bounded whatever the value (a YAML alias bomb, a self-containing list, a 5,000-digit
    integer, which plain ``repr`` refuses to print)."""

    def __init__(self):
        super().__init__()
        self.maxlevel, self.maxlist, self.maxtuple, self.maxdict = 3, 6, 6, 6
        self.maxstring, self.maxother = 60, 60

    def repr_int(self, x, level):
        if x.bit_length() > 200:  # more than about 60 digits
            return f"<an integer of about {int(x.bit_length() * 0.30103):,} digits>"
        return repr(x)


_bounded = _BoundedRepr()


def bounded_repr(value: object, limit: int = 80) -> str:
    """``repr(value)`` for a message: at most ``limit`` characters, at a bounded cost."""
    shown = _bounded.repr(value)
    return shown if len(shown) <= limit else shown[:limit - 3] + "..."


def one_paragraph(text: str) -> str:
    """``text`` on one line (any line breaks or runs of spaces a quoted message brings become
    one space), at most ``MAX_MESSAGE`` characters."""
    text = " ".join(str(text).split())
    return text if len(text) <= MAX_MESSAGE else text[:MAX_MESSAGE - 3] + "..."


class HemiradInputError(Exception):
    """Bad input from the user: a scene file, a mesh file, an option or an output path.

    The message is one self-contained paragraph (made so here, whatever it quotes); the
    CLI prints it without a traceback.
    """

    def __init__(self, message: str = ""):
        super().__init__(one_paragraph(message))


class SceneError(HemiradInputError):
    """A problem at one key of a scene file.

    Args:
        file: the scene file's path as the user gave it.
        key: the key path inside the file, e.g. ``objects[3].material``.
        expected: what the key should hold, e.g. ``"three numbers in [0, 1)"``.
        got: what it holds (optional; shown with a bounded ``repr``).
        hint: an extra sentence, e.g. a did-you-mean.
    """

    def __init__(self, file: str, key: str, expected: str, got: object = ..., hint: str = ""):
        self.file, self.key, self.expected, self.got, self.hint = file, key, expected, got, hint
        where = f"{file}: {key}" if key else str(file)
        text = f"{where}: expected {expected}"
        if got is not ...:
            text += f", got {bounded_repr(got)}"
        text += "."
        if hint:
            text += f" {hint}"
        super().__init__(text)


class HemiradWarning(UserWarning):
    """Something in the input was repaired or dropped; the run goes on (e.g. degenerate triangles)."""
