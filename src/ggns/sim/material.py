"""Material parameters of the deformable body and their validation."""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class Material:
    """Isotropic linear-elastic material with Rayleigh damping.

    youngs_modulus: E in Pa, > 0.
    poissons_ratio: nu, -1 < nu < 0.5 (auxetic nu < 0 included).
    density: mass per volume in kg/m^3 (2D plane strain: per unit thickness).
    rayleigh_mass: alpha in 1/s, damping force -alpha * M v.
    rayleigh_stiffness: beta in s, damping force -beta * K v.
    """

    youngs_modulus: float
    poissons_ratio: float
    density: float = 1000.0
    rayleigh_mass: float = 0.0
    rayleigh_stiffness: float = 0.0

    def __post_init__(self) -> None:
        e, nu = self.youngs_modulus, self.poissons_ratio
        if not (math.isfinite(e) and e > 0):
            raise ValueError(f"Young's modulus must be finite and > 0 Pa, got E = {e}")
        if not (math.isfinite(nu) and -1.0 < nu < 0.5):
            raise ValueError(
                f"Poisson's ratio must satisfy -1 < nu < 0.5 (the range where linear elasticity "
                f"is stable), got nu = {nu}"
            )
        if not (math.isfinite(self.density) and self.density > 0):
            raise ValueError(f"density must be finite and > 0 kg/m^3, got {self.density}")
        for name in ("rayleigh_mass", "rayleigh_stiffness"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {value}")

    @property
    def lame(self) -> tuple[float, float]:
        """Lame parameters (lambda, mu) in Pa; plane strain uses the same pair in 2D."""
        e, nu = self.youngs_modulus, self.poissons_ratio
        return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))
