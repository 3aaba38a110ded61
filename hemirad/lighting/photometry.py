"""Photometric units: lux from irradiance, luminance from radiosity, a luminous flux made an exitance.

The convention: a colour's Rec. 709 luminance (``core.colour.luminance``) is its photometric
amount. In a photometric scene exitances are in lm/m^2, so an irradiance's luminance is its
illuminance in lux; in a radiometric one they are in W/m^2, and lux is ``LUMENS_PER_WATT``
(683 lm/W) times that luminance. A Lambertian surface of (luminous) exitance B has luminance
B / pi (cd/m^2 when B is in lm/m^2).
"""
from __future__ import annotations

import math

import torch

from hemirad.core.colour import LUMENS_PER_WATT, luminance
from hemirad.geometry.mesh import Mesh
from hemirad.scene.model import UNITS, Scene


def lumens_per_unit(units: str) -> float:
    """Lumens per unit of the scene's power: 1 for photometric, 683 for radiometric (W)."""
    if units not in UNITS:
        raise ValueError(f"units must be one of {', '.join(UNITS)}, got {units!r}")
    return 1.0 if units == "photometric" else LUMENS_PER_WATT


def illuminance(irradiance: torch.Tensor, units: str) -> torch.Tensor:
    """(..., 3) irradiance in the scene's exitance unit -> (...) illuminance in lux."""
    return luminance(irradiance) * lumens_per_unit(units)


def luminance_cd(radiosity: torch.Tensor, units: str) -> torch.Tensor:
    """(..., 3) radiosity of Lambertian surfaces -> (...) their luminance in cd/m^2."""
    return illuminance(radiosity, units) / math.pi


def flux_exitance(flux: float, area_m2: float, colour, units: str) -> torch.Tensor:
    """(3,) float64 the exitance (lm/m^2 or W/m^2 by ``units``) of ``area_m2`` square metres
    giving ``flux`` lumens evenly, in the colour ``colour`` (3,): the colour scaled so that
    its luminance is flux / area (divided by 683 lm/W for a radiometric scene)."""
    colour = torch.as_tensor(colour, dtype=torch.float64)
    return colour / luminance(colour) * (flux / area_m2 / lumens_per_unit(units))


def material_areas(mesh: Mesh, num_materials: int) -> torch.Tensor:
    """(M,) float64 the area of every material's elements in the mesh (scene units^2)."""
    return torch.zeros(num_materials, dtype=torch.float64).index_add_(
        0, mesh.material.cpu(), mesh.areas.cpu().to(torch.float64))


def flux_emissions(scene: Scene, mesh: Mesh) -> dict[str, dict]:
    """What each material given by ``flux`` emits once meshed: ``{name: {"flux_lm",
    "area_m2", "exitance"}}``, the exitance (3 numbers) its flux spread over all its
    elements' area. A material no element uses is left out."""
    areas = material_areas(mesh, len(scene.materials)) * scene.metres_per_unit ** 2
    out = {}
    for index, material in enumerate(scene.materials):
        if material.flux is None or not float(areas[index]) > 0:
            continue
        exitance = flux_exitance(material.flux, float(areas[index]), material.colour, scene.units)
        out[material.name] = {"flux_lm": material.flux, "area_m2": float(areas[index]),
                              "exitance": exitance.tolist()}
    return out


def emission_table(scene: Scene, mesh: Mesh) -> torch.Tensor:
    """(M, 3) float64 every material's emitted exitance, a flux made an exitance over the
    material's area in ``mesh`` (the initial mesh: splitting keeps areas)."""
    table = scene.emission_table()
    fluxes = flux_emissions(scene, mesh)
    for index, material in enumerate(scene.materials):
        if material.name in fluxes:
            table[index] = torch.tensor(fluxes[material.name]["exitance"], dtype=torch.float64)
    return table
