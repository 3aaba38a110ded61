"""Errors a user can cause, reported as one paragraph and exit code 2 by the CLI."""
from __future__ import annotations


class HemiradInputError(Exception):
    """Bad input from the user: a scene file, a mesh file, an option or an output path.

    The message is one self-contained paragraph; the CLI prints it without a traceback.
    """


class SceneError(HemiradInputError):
    """A problem at one key of a scene file.

    Args:
        file: the scene file's path as the user gave it.
        key: the key path inside the file, e.g. ``objects[3].material``.
        expected: what the key should hold, e.g. ``"three numbers in [0, 1)"``.
        got: what it holds (optional; shown with ``repr``).
        hint: an extra sentence, e.g. a did-you-mean.
    """

    def __init__(self, file: str, key: str, expected: str, got: object = ..., hint: str = ""):
        self.file, self.key, self.expected, self.got, self.hint = file, key, expected, got, hint
        where = f"{file}: {key}" if key else str(file)
        text = f"{where}: expected {expected}"
        if got is not ...:
            shown = repr(got)
            text += f", got {shown if len(shown) <= 80 else shown[:77] + '...'}"
        text += "."
        if hint:
            text += f" {hint}"
        super().__init__(text)


class HemiradWarning(UserWarning):
    """Something in the input was repaired or dropped; the run goes on (e.g. degenerate triangles)."""
