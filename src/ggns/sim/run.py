"""Run the simulator along prescribed collider paths and record every frame."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from .fem import ElasticBody
from .material import Material
from .solver import Collider, SimulationError, Simulator, SolverConfig

DIAGNOSTICS = {
    "newton_iterations": "Newton iterations spent reaching this frame",
    "max_penetration": "max depth of a mesh node inside a collider at this frame, m",
    "kinetic_energy": "kinetic energy at this frame, J",
    "elastic_energy": "elastic energy at this frame, J",
    "contact_work": "work of the contact forces on the body since the previous frame, J",
}
# A frame whose step fails (Newton or its line search does not converge) is simulated again from its start
# with twice the substeps, up to 2**REFINEMENTS times as many, before the failure is reported. Such a
# trajectory's diagnostics then hold REFINED: the substeps each frame took (absent where none was retried,
# so every trajectory that never failed is what it was without retries, bit for bit).
REFINEMENTS = 3
REFINED = "substeps"


def simulate(
    rest_positions: np.ndarray,
    cells: np.ndarray,
    fixed: np.ndarray,
    material: Material,
    solver: SolverConfig,
    collider_paths: list[tuple[np.ndarray, np.ndarray]],
    substeps: int = 1,
    fixed_paths: np.ndarray | None = None,
) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Simulate from rest with zero velocity. collider_paths: per collider (vertices per frame
    [T, K, d], faces [F, d]; faces may be empty for a collider that only moves fixed nodes);
    vertices move linearly between frames, and solver.dt is the frame interval divided by
    `substeps`. fixed_paths: [T, N, d] prescribed positions of the fixed nodes per frame (a
    grasped node following a gripper; entries of free nodes are ignored; frame 0 must be the rest
    state), moving linearly between frames; default: fixed nodes stay at rest. Returns positions
    [T, N, d] and per-frame diagnostics [T]."""
    if substeps < 1:
        raise ValueError(f"substeps must be >= 1, got {substeps}")
    T = collider_paths[0][0].shape[0] if collider_paths else None
    if T is None or any(path.shape[0] != T for path, _ in collider_paths):
        raise ValueError("every collider path needs the same number of frames T >= 1")
    fixed_mask = np.asarray(fixed, dtype=bool)
    if fixed_paths is not None:
        fixed_paths = np.asarray(fixed_paths, dtype=np.float64)
        if fixed_paths.shape != (T,) + np.shape(rest_positions):
            raise ValueError(f"fixed_paths must be [T, N, d] = {(T,) + np.shape(rest_positions)}, got {fixed_paths.shape}")
        if not np.isfinite(fixed_paths[:, fixed_mask]).all():
            raise ValueError("fixed_paths holds NaN or infinite positions of fixed nodes")
        if not np.allclose(fixed_paths[0, fixed_mask], np.asarray(rest_positions)[fixed_mask]):
            raise ValueError("fixed_paths[0] must hold the fixed nodes' rest positions (simulations start at rest)")
    X = torch.as_tensor(rest_positions, dtype=torch.float64)
    body = ElasticBody(X, torch.as_tensor(cells), material)
    sim = Simulator(body, torch.as_tensor(fixed), solver)
    paths = [(torch.as_tensor(p, dtype=torch.float64), torch.as_tensor(f, dtype=torch.long)) for p, f in collider_paths
             if len(f) > 0]  # a collider without faces has no contact surface
    prescribed = None if fixed_paths is None else torch.as_tensor(fixed_paths)
    x, v = X.clone(), torch.zeros_like(X)
    positions = np.empty((T,) + X.shape)
    positions[0] = X.numpy()
    diag = {name: np.zeros(T) for name in DIAGNOSTICS}
    diag["elastic_energy"][0] = body.energy(x).item()
    simulators = {substeps: sim}  # per substep count; a retried frame builds the finer one
    taken = np.full(T, substeps)
    for t in range(1, T):
        start, multipliers = (x, v), list(sim.multipliers)  # contact multipliers are warm-started over steps
        n = substeps
        while True:
            if n not in simulators:
                simulators[n] = Simulator(body, torch.as_tensor(fixed), replace(solver, dt=solver.dt * substeps / n))
            stepper = simulators[n]
            stepper.multipliers = list(multipliers)
            (x, v), iterations, work, penetration = start, 0.0, 0.0, 0.0
            try:
                for s in range(1, n + 1):
                    w = s / n
                    colliders = [Collider((1 - w) * p[t - 1] + w * p[t], f) for p, f in paths]
                    targets = None if prescribed is None else (1 - w) * prescribed[t - 1] + w * prescribed[t]
                    x, v, info = stepper.step(x, v, colliders, fixed_positions=targets)
                    iterations += info.newton_iterations
                    work += info.contact_work
                    penetration = max(penetration, info.max_penetration)
                break
            except SimulationError as error:
                if n >= substeps * 2**REFINEMENTS:
                    retried = f" (the frame retried with up to {n} substeps)" if n > substeps else ""
                    raise SimulationError(f"frame {t}, substep {s}: {error}{retried}") from None
                n *= 2
        sim.multipliers = stepper.multipliers
        taken[t] = n
        diag["newton_iterations"][t] += iterations
        diag["contact_work"][t] += work
        diag["max_penetration"][t] = max(diag["max_penetration"][t], penetration)
        positions[t] = x.numpy()
        diag["kinetic_energy"][t] = sim.kinetic_energy(v)
        diag["elastic_energy"][t] = body.energy(x).item()
    if (taken > substeps).any():
        diag[REFINED] = taken.astype(np.float64)
    return positions, diag
