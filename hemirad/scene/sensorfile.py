"""A sensor file (``--sensors FILE``): one sensor a line, ``x,y,z,nx,ny,nz[,name]``.

    # desks, 0.75 m up, facing the ceiling
    x,y,z,nx,ny,nz,name
    1.0,0.75,2.5,0,1,0,desk A
    2.0,0.75,2.5,0,1,0

A first line whose first value is not a number is a header; ``#`` starts a comment (to
the end of the line); blank lines are skipped. Each mistake is one paragraph naming the
file and the line.
"""
from __future__ import annotations

import csv
import math
from pathlib import Path

from hemirad.core.errors import HemiradInputError, bounded_repr
from hemirad.scene.keys import MAX_COORDINATE
from hemirad.scene.model import Sensor
from hemirad.scene.sensorblocks import MAX_SENSORS

_COLUMNS = "x,y,z,nx,ny,nz[,name]"


def _number(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def read_sensor_file(path, taken: set[str] = frozenset(), first_index: int = 0) -> list[Sensor]:
    """The sensors of the file at ``path``.

    Args:
        taken: names already used (the scene file's sensors); a sensor here may not reuse one.
        first_index: the number in the default name (``sensor<i>``) of the file's first sensor.
    Raises:
        HemiradInputError: the file cannot be read, holds no sensor, or a line is not
            six numbers (a non-zero normal among them) and an optional name.
    """
    shown = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8-sig")  # a spreadsheet's byte-order mark is dropped
    except FileNotFoundError as exc:
        raise HemiradInputError(f"the sensor file {shown} does not exist.") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise HemiradInputError(f"cannot read the sensor file {shown} as UTF-8 text: {exc}.") from exc
    sensors, names = [], {name: None for name in taken}
    seen_data = False
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].strip()
        if not content:
            continue
        where = f"{shown}, line {number}"
        fields = [f.strip() for f in next(csv.reader([content]))]
        if not seen_data and fields and _number(fields[0]) is None:
            seen_data = True  # a header: only the first line with values may be one
            continue
        seen_data = True
        if len(fields) not in (6, 7):
            raise HemiradInputError(f"{where}: expected 6 or 7 comma-separated values ({_COLUMNS}), "
                                    f"got {len(fields)}: {bounded_repr(content)}.")
        values = [_number(f) for f in fields[:6]]
        for column, (field, value) in enumerate(zip(fields, values)):
            if value is None or not math.isfinite(value):
                raise HemiradInputError(f"{where}: expected a finite number for {_COLUMNS.split(',')[column]} "
                                        f"(column {column + 1}), got {bounded_repr(field)}.")
            if abs(value) > MAX_COORDINATE:
                raise HemiradInputError(f"{where}: expected a coordinate within +-{MAX_COORDINATE:g} for "
                                        f"{_COLUMNS.split(',')[column]} (column {column + 1}), got {field}.")
        if not any(values[3:]):
            raise HemiradInputError(f"{where}: expected a non-zero normal nx,ny,nz (the way the sensor faces), "
                                    f"got {','.join(fields[3:6])}.")
        name = fields[6] if len(fields) == 7 and fields[6] else f"sensor{first_index + len(sensors)}"
        if len(name) > 200:
            raise HemiradInputError(f"{where}: expected a sensor name of at most 200 characters, "
                                    f"got {bounded_repr(name)}.")
        if name in names:
            other = f"line {names[name]}" if names[name] is not None else "a sensor of the scene file"
            raise HemiradInputError(f"{where}: expected a sensor name no other sensor has, got {name!r} "
                                    f"({other} has it too).")
        names[name] = number
        if len(sensors) + len(taken) >= MAX_SENSORS:
            raise HemiradInputError(f"{where}: a scene may have at most {MAX_SENSORS:,} sensors (each is a "
                                    f"hemicube rendered), and this line makes one more.")
        sensors.append(Sensor(tuple(values[:3]), tuple(values[3:]), name))
    if not sensors:
        raise HemiradInputError(f"the sensor file {shown} holds no sensor: expected lines {_COLUMNS}.")
    return sensors
