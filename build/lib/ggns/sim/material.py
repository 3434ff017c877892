"""Material parameters of the deformable body and their validation.

2D bodies are slices of a 3D body, in one of two idealizations (`plane`):
- "stress": a thin plate, free to contract through its thickness (sigma_zz = 0). Its in-plane
  material matrix is E / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]], i.e. the
  Lame pair (lambda*, mu) with lambda* = 2 lambda mu / (lambda + 2 mu) = E nu / (1 - nu^2).
  This is what SOFA's TriangularFEMForceField computes, so the paper's plate is plane stress.
- "strain": a slice of a long prism (eps_zz = 0), Lame pair (lambda, mu) as in 3D; near
  nu = 0.5 it is nearly incompressible in the plane, and linear triangles then lock.
3D bodies ignore `plane`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

PLANES = ("strain", "stress")


@dataclass(frozen=True)
class Material:
    """Isotropic linear-elastic material with Rayleigh damping.

    youngs_modulus: E in Pa, > 0.
    poissons_ratio: nu, -1 < nu < 0.5 (auxetic nu < 0 included).
    density: mass per volume in kg/m^3 (2D: per unit thickness).
    rayleigh_mass: alpha in 1/s, damping force -alpha * M v.
    rayleigh_stiffness: beta in s, damping force -beta * K v.
    plane: 2D idealization, "strain" or "stress" (module docstring); unused in 3D.
    """

    youngs_modulus: float
    poissons_ratio: float
    density: float = 1000.0
    rayleigh_mass: float = 0.0
    rayleigh_stiffness: float = 0.0
    plane: str = "strain"

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
        if self.plane not in PLANES:
            raise ValueError(f"plane must be one of {PLANES} (the 2D idealization), got {self.plane!r}")

    @classmethod
    def of_scene(cls, scene: dict, youngs_modulus: float, poissons_ratio: float) -> Material:
        """E and nu with a scene config's density, Rayleigh damping and (2D) `plane`."""
        return cls(float(youngs_modulus), float(poissons_ratio), scene["density"], scene["rayleigh_mass"],
                   scene["rayleigh_stiffness"], plane=scene.get("plane", "strain"))

    @classmethod
    def listed(cls, scene: dict, index: int) -> Material:
        """Entry `index` of a scene config's `materials` list ({youngs_modulus, poissons_ratio}; the
        tissue and the cavity) with the scene's density and damping."""
        entry = scene["materials"][index]
        return cls.of_scene(scene, entry["youngs_modulus"], entry["poissons_ratio"])

    @property
    def lame(self) -> tuple[float, float]:
        """3D Lame parameters (lambda, mu) in Pa (also the 2D plane-strain pair)."""
        e, nu = self.youngs_modulus, self.poissons_ratio
        return e * nu / ((1 + nu) * (1 - 2 * nu)), e / (2 * (1 + nu))

    def lame_parameters(self, dim: int) -> tuple[float, float]:
        """The Lame pair (lambda, mu) in Pa that a `dim`-D body uses: in 2D plane stress
        lambda* = 2 lambda mu / (lambda + 2 mu) = E nu / (1 - nu^2); otherwise `lame`."""
        if dim not in (2, 3):
            raise ValueError(f"dim must be 2 or 3, got {dim}")
        lam, mu = self.lame
        if dim == 2 and self.plane == "stress":
            return 2 * lam * mu / (lam + 2 * mu), mu
        return lam, mu
