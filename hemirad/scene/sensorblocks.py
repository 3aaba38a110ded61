"""The loader's checks of a scene's measuring keys: ``units``, ``unit``, ``sensors`` and ``grids``.

    units: photometric               # emissions in lm/m^2, results in lux; default radiometric
    unit: cm                         # metres per scene unit: m, cm, mm, ... or a number; default m
    sensors:
      - {position: [1, 0.75, 1], normal: [0, 1, 0], name: desk}
    grids:
      - {name: desk, work_plane: {height: 0.75, min: [1.8, 2.2], max: [3.2, 2.9]}}
      - {name: wall, origin: [0, 0.5, 0], u: [2, 0, 0], v: [0, 1.5, 0], normal: [0, 0, 1], spacing: 0.25}
"""
from __future__ import annotations

import math
import re

import numpy as np

from hemirad.scene.keys import Checker, did_you_mean, is_number
from hemirad.scene.model import UNITS, Grid, Sensor

#: Length units by name, in metres.
LENGTH_UNITS = {"m": 1.0, "dm": 0.1, "cm": 0.01, "mm": 0.001, "um": 1e-6, "km": 1000.0,
                "in": 0.0254, "ft": 0.3048, "yd": 0.9144}

#: A grid's name becomes part of a file name (``grid_<name>.csv``): letters, digits, ``_.-``.
GRID_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}")

#: How far from perpendicular (the cosine of the angle) a grid's ``u`` and ``v`` may be.
PERPENDICULAR_TOLERANCE = 1e-6

#: The most sensors a scene (its file and a sensor file together) may have: each is a hemicube.
MAX_SENSORS = 10_000

_SENSOR_KEYS = ("position", "normal", "name")
_GRID_KEYS = ("name", "work_plane", "origin", "u", "v", "normal", "spacing")
_WORK_PLANE_KEYS = ("height", "min", "max")
UP = (0.0, 1.0, 0.0)


def read_units(check: Checker, v) -> str:
    return check.choice(v, "units", UNITS)


def read_length_unit(check: Checker, v) -> float:
    """Metres per scene unit, from a unit's name (``cm``) or a number of metres."""
    expected = f"a length unit ({', '.join(LENGTH_UNITS)}) or the number of metres in one scene unit"
    if is_number(v):
        return check.bounded(v, "unit", expected, lambda x: 1e-12 <= x <= 1e12)
    if not isinstance(v, str) or v not in LENGTH_UNITS:
        check.fail("unit", expected, v, did_you_mean(v, LENGTH_UNITS))
    return LENGTH_UNITS[v]


def non_zero_direction(check: Checker, v, key: str, what: str) -> tuple[float, float, float]:
    """Three numbers that are not all zero (a normal or an edge)."""
    d = check.vec3(v, key, f"three numbers [x, y, z], {what}")
    if not any(d):
        check.fail(key, f"a non-zero direction ({what})", list(d))
    return d


def read_sensors(check: Checker, v) -> list[Sensor]:
    expected = "a list of sensors {position: [x, y, z], normal: [nx, ny, nz], name: optional}"
    if not isinstance(v, list):
        check.fail("sensors", expected, v)
    if len(v) > MAX_SENSORS:
        check.fail("sensors", f"at most {MAX_SENSORS:,} sensors (each is a hemicube rendered)", f"{len(v)} sensors")
    sensors, names = [], {}
    for i, spec in enumerate(v):
        key = f"sensors[{i}]"
        spec = check.section(spec, key, expected, _SENSOR_KEYS, ("position", "normal"))
        position = check.point(spec["position"], f"{key}.position")
        normal = non_zero_direction(check, spec["normal"], f"{key}.normal", "the way the sensor faces")
        name = spec.get("name", f"sensor{i}")
        if not isinstance(name, str) or not name.strip() or len(name) > 200:
            check.fail(f"{key}.name", "a non-empty name of at most 200 characters", name)
        if name in names:
            check.fail(f"{key}.name", "a name no other sensor has", name, f"{names[name]} is also called {name!r}.")
        names[name] = key
        sensors.append(Sensor(position, normal, name))
    return sensors


def read_grids(check: Checker, v) -> list[Grid]:
    expected = "a list of grids, each {name, work_plane: {height, min, max}} or {name, origin, u, v}"
    if not isinstance(v, list):
        check.fail("grids", expected, v)
    grids, names = [], {}
    for i, spec in enumerate(v):
        grid = read_grid(check, spec, f"grids[{i}]", f"grid{i}")
        if grid.name in names:
            check.fail(f"grids[{i}].name", "a name no other grid has", grid.name,
                       f"{names[grid.name]} is also called {grid.name!r}.")
        names[grid.name] = grid.key
        grids.append(grid)
    return grids


def read_grid(check: Checker, spec, key: str, default_name: str) -> Grid:
    spec = check.section(spec, key, "a grid mapping: {name, work_plane: {height, min, max}} or "
                                    "{name, origin, u, v}, with optional normal and spacing", _GRID_KEYS)
    name = spec.get("name", default_name)
    if not isinstance(name, str) or not GRID_NAME.fullmatch(name):
        check.fail(f"{key}.name", "a name of 1 to 64 letters, digits, '_', '.' or '-', not starting with '.' or "
                                  "'-' (it names the file grid_<name>.csv)", name)
    rectangle = [k for k in ("origin", "u", "v") if k in spec]
    if "work_plane" in spec:
        if rectangle:
            check.fail(f"{key}.{rectangle[0]}", "either work_plane or origin, u and v, not both", spec[rectangle[0]])
        origin, u, v = _work_plane(check, spec["work_plane"], f"{key}.work_plane")
        default_normal = UP
    else:
        for k in ("origin", "u", "v"):
            if k not in spec:
                check.fail(f"{key}.{k}", "a work_plane {height, min, max}, or a corner origin and two "
                                         "perpendicular edges u and v", hint="The key is missing.")
        origin = check.point(spec["origin"], f"{key}.origin", "three numbers [x, y, z], a corner of the grid")
        u = non_zero_direction(check, spec["u"], f"{key}.u", "the edge from origin to the next corner")
        v = non_zero_direction(check, spec["v"], f"{key}.v", "the other edge from origin")
        for edge, vector in (("u", u), ("v", v)):
            if max(abs(x) for x in vector) > 1e15:
                check.fail(f"{key}.{edge}", "an edge within +-1e15", list(vector))
        a, b = np.asarray(u) / np.abs(u).max(), np.asarray(v) / np.abs(v).max()
        cosine = abs(float(a @ b)) / (np.linalg.norm(a) * np.linalg.norm(b))
        if cosine > PERPENDICULAR_TOLERANCE:
            check.fail(f"{key}.v", "an edge perpendicular to u (the grid is a rectangle)", list(v),
                       f"The angle between u and v is {math.degrees(math.acos(min(cosine, 1.0))):.4g} degrees.")
        default_normal = tuple(float(x) for x in np.cross(a, b) / np.linalg.norm(np.cross(a, b)))
    normal = default_normal
    if "normal" in spec:
        normal = non_zero_direction(check, spec["normal"], f"{key}.normal", "the way the grid's sensors face")
    spacing = None
    if "spacing" in spec:
        spacing = check.bounded(spec["spacing"], f"{key}.spacing", "a distance between points > 0 (scene units)",
                                lambda x: 0 < x < 1e15)
    return Grid(name, origin, u, v, normal, spacing, key)


def _work_plane(check: Checker, v, key: str):
    """A horizontal rectangle at ``height``: (origin, u, v) along x and z."""
    m = check.section(v, key, "a mapping {height, min: [x, z], max: [x, z]}", _WORK_PLANE_KEYS,
                      ("height", "min", "max"))
    height = check.number(m["height"], f"{key}.height", "a height (the y coordinate of the plane)")
    corners = []
    for k in ("min", "max"):
        c = m[k]
        if not isinstance(c, (list, tuple)) or len(c) != 2:
            check.fail(f"{key}.{k}", "two numbers [x, z]", c)
        corners.append(tuple(check.number(x, f"{key}.{k}[{i}]", "a finite number") for i, x in enumerate(c)))
    for value, where in ((height, f"{key}.height"), *((x, f"{key}.min") for x in corners[0]),
                         *((x, f"{key}.max") for x in corners[1])):
        if abs(value) > 1e15:
            check.fail(where, "coordinates within +-1e15", value)
    (x0, z0), (x1, z1) = corners
    for axis, a, b in (("x", x0, x1), ("z", z0, z1)):
        if not a < b:
            check.fail(f"{key}.max", "a point above min in x and in z", list(corners[1]),
                       f"On axis {axis}, min is {a:g} and max is {b:g}.")
    return (x0, height, z0), (x1 - x0, 0.0, 0.0), (0.0, 0.0, z1 - z0)
