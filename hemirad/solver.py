"""Progressive-refinement radiosity (Cohen, Chen, Wallace & Greenberg 1988), RGB.

The state is per element: radiosity B and unshot radiosity dB, (T, 3) float64 each. A shot
takes the element with the most unshot power, renders its hemicube, and hands every
receiver j the radiosity  rho_j dB_s F_sj A_s / A_j  (DESIGN §1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import torch

from .formfactor import HemicubeFormFactors
from .mesh import Mesh


def received_radiosity(form_factors: torch.Tensor, shot_power: torch.Tensor,
                       reflectance: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """Radiosity each receiver reflects from one shot.

    Args:
        form_factors: (T,) F_sj from the shooter to every element.
        shot_power: (3,) the shooter's unshot power dB_s A_s.
        reflectance: (T, 3) rho_j.
        areas: (T,) A_j.
    Returns:
        (T, 3) rho_j F_sj dB_s A_s / A_j.
    """
    return reflectance * (form_factors / areas)[:, None] * shot_power[None, :]


def ambient_term(unshot: torch.Tensor, reflectance: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """Cohen et al.'s ambient radiosity: the unshot power, spread evenly and inter-reflected.

    Args:
        unshot: (T, 3) dB; reflectance: (T, 3); areas: (T,).
    Returns:
        (3,) ambient radiosity; element j is displayed as B_j + rho_j * ambient.
    """
    total_area = areas.sum()
    mean_reflectance = (reflectance * areas[:, None]).sum(0) / total_area
    mean_unshot = (unshot * areas[:, None]).sum(0) / total_area
    return mean_unshot / (1.0 - mean_reflectance)


@dataclass
class SolverState:
    """Everything a solve has computed so far.

    Attributes:
        radiosity: (T, 3) B.
        unshot: (T, 3) dB.
        shots: shots done.
        absorbed: (3,) power absorbed by receivers, (1 - rho) of what reached their front.
        escaped: (3,) power that reached no element's front (open scenes, back faces).
    """

    radiosity: torch.Tensor
    unshot: torch.Tensor
    shots: int = 0
    absorbed: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))
    escaped: torch.Tensor = field(default_factory=lambda: torch.zeros(3, dtype=torch.float64))


@dataclass
class ShotReport:
    shots: int
    shooter: int
    elements: int
    unshot_fraction: float
    seconds: float


class ProgressiveSolver:
    """Shoots until a shot count or an unshot-energy fraction is reached.

    Args:
        mesh: the elements.
        reflectance, emission: (T, 3) per element.
        resolution: hemicube resolution R.
    """

    def __init__(self, mesh: Mesh, reflectance: torch.Tensor, emission: torch.Tensor, resolution: int):
        self.mesh = mesh
        self.reflectance = reflectance
        self.emission = emission
        self.areas = mesh.areas
        self.state = SolverState(radiosity=emission.clone(), unshot=emission.clone())
        self.emitted_power = (emission * self.areas[:, None]).sum(0)  # (3,)
        self.form_factors = HemicubeFormFactors(mesh.corners, resolution)
        self.update_seconds = 0.0

    def close(self) -> None:
        self.form_factors.close()

    @property
    def unshot_fraction(self) -> float:
        unshot_power = (self.state.unshot * self.areas[:, None]).sum()
        return float(unshot_power / self.emitted_power.sum())

    def shoot(self) -> int | None:
        """One shot from the element with the largest unshot power; None when nothing is left."""
        state = self.state
        power = state.unshot * self.areas[:, None]  # (T, 3)
        shooter = int(torch.argmax(power.sum(1)))
        shot_power = power[shooter].clone()
        if float(shot_power.sum()) <= 0.0:
            return None
        F = self.form_factors.from_element(shooter)
        start = time.perf_counter()
        delta = received_radiosity(F, shot_power, self.reflectance, self.areas)
        state.radiosity += delta
        state.unshot += delta
        state.unshot[shooter] = 0.0
        state.absorbed += ((1.0 - self.reflectance) * F[:, None]).sum(0) * shot_power
        state.escaped += (1.0 - F.sum()) * shot_power
        state.shots += 1
        self.update_seconds += time.perf_counter() - start
        return shooter

    def run(self, max_shots: int, unshot_fraction: float,
            progress: Callable[[ShotReport], None] | None = None) -> SolverState:
        start = time.perf_counter()
        while self.state.shots < max_shots and self.unshot_fraction > unshot_fraction:
            shooter = self.shoot()
            if shooter is None:
                break
            if progress is not None:
                progress(ShotReport(self.state.shots, shooter, self.mesh.num_elements,
                                    self.unshot_fraction, time.perf_counter() - start))
        return self.state

    def timings(self) -> dict[str, float]:
        return {**self.form_factors.timings(), "update": self.update_seconds}
