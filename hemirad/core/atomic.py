"""Files written whole or not at all: a temporary file beside the target, then ``os.replace``.

A run killed (or a disk filling up) while writing leaves the previous file, never a
truncated one; the temporary files such a run leaves are named by ``temporary_path`` so a
later run in the same folder can find and remove them (``remove_stale_temporaries``).
"""
from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import BinaryIO, Callable

_SUFFIX = ".tmp"


def temporary_path(path: Path) -> Path:
    """Where ``path`` is written before it is moved into place: beside it (``os.replace`` is
    atomic only within one file system), hidden, with the process id so two runs never share one."""
    return path.parent / f".{path.name}.{os.getpid()}{_SUFFIX}"


def write_atomically(path, write: Callable[[BinaryIO], None]) -> None:
    """Call ``write(file)`` on a temporary file, make it durable, and move it over ``path``.

    Raises:
        OSError: the folder or the file cannot be written (the temporary file is removed).
    """
    def write_file(tmp: Path) -> None:
        with open(tmp, "wb") as f:  # opened normally, so the file gets the usual permissions
            write(f)

    write_atomically_by_name(path, write_file)


def write_atomically_by_name(path, write: Callable[[Path], None]) -> None:
    """Call ``write(temporary_path)`` (a writer that opens the file itself, by name: a
    library that takes a path, not a file object), make the file durable, and move it
    over ``path``.

    Raises:
        OSError: the folder or the file cannot be written (the temporary file is removed).
    """
    path = Path(path)
    tmp = temporary_path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)  # on disk before the rename makes it the file
        finally:
            os.close(fd)
        os.replace(tmp, path)
        tmp = None
    finally:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()


def remove_stale_temporaries(folder, names) -> list[Path]:
    """Remove the temporary files a killed run left for the files ``names`` in ``folder``;
    only safe while no other run writes there. Returns what was removed."""
    removed = []
    for name in names:
        for tmp in Path(folder).glob(f".{name}.*{_SUFFIX}"):
            if tmp.name[len(name) + 2:-len(_SUFFIX)].isdigit():  # .<name>.<pid>.tmp
                with contextlib.suppress(OSError):
                    tmp.unlink()
                    removed.append(tmp)
    return removed
