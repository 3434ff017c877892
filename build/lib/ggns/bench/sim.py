"""`python -m ggns bench sim`: the ground-truth simulator and the depth sensor, timed trajectory by
trajectory on one thread (as a generation worker runs), and optionally the generation of all of a
preset's splits with its worker count."""
from __future__ import annotations

import math
import platform
import statistics
import tempfile
import time
from collections.abc import Sequence

import numpy as np
import torch

from ..config import load_config
from ..data.generate import generate, trajectory_seed
from ..geometry import box_tet_mesh, min_volume_ratio
from ..scenes import SCENES
from ..sensors.camera import DepthSensor, SensorConfig
from ..sim.fem import ElasticBody
from ..sim.material import Material
from ..sim.solver import SimulationError, Simulator, SolverConfig
from .timing import median_ms, time_trajectories


def bench_sim(preset: str = "plate", trajectories: int = 9, generate_splits: bool = False, overrides=()) -> dict:
    """Time the ground-truth simulator and the depth sensor trajectory by trajectory on one thread
    (as a generation worker runs), over `trajectories` of the preset's training jobs spread over its
    shape x material combinations; with `generate_splits`, also the generation of all the preset's
    splits with its worker count; `overrides` (key=value) change the preset, e.g.
    solver.linear_solver=sparse. Prints and returns the medians."""
    config = load_config(preset, list(overrides))
    scene_module = SCENES[config["scene"]["name"]]
    sensor = DepthSensor(SensorConfig.from_dict(config["sensor"]))
    combos = scene_module.num_combinations(config["scene"])
    jobs = [((i * 7) % combos, trajectory_seed(config["seed"], "train", i)) for i in range(trajectories)]
    sim_step, sensor_step, whole, newton = [], [], [], []
    for seconds, traj in time_trajectories(scene_module, config, jobs, sensor):
        whole.append(seconds)
        # observe the recorded states again to split the time between sensor and simulator
        start = time.perf_counter()
        for t in range(traj.num_steps):
            sensor.observe(traj.positions[t], traj.cells, traj.collider_positions[t], traj.collider_faces)
        observe = time.perf_counter() - start
        sensor_step.append(observe / traj.num_steps)
        sim_step.append((seconds - observe) / (traj.num_steps - 1))
        newton.append(traj.diagnostics["newton_iterations"][1:].mean())
    result = {
        "machine": f"{platform.processor() or platform.machine()}, 1 torch thread",
        "simulator ms/step (median, incl. scene set-up)": median_ms(sim_step),
        "sensor ms/step (median)": median_ms(sensor_step),
        "trajectory s (median, simulate + observe)": statistics.median(whole),
        "Newton iterations/step (mean)": float(np.mean(newton)),
        "trajectories timed": trajectories,
    }
    if generate_splits:
        total = sum(config["splits"].values())
        with tempfile.TemporaryDirectory() as out:
            start = time.perf_counter()
            generate(dict(config, output=out), progress=True)
            elapsed = time.perf_counter() - start
        result[f"generate all splits ({total} trajectories, {config['workers']} workers) s"] = elapsed
    print(f"bench sim: preset {preset!r}{' with ' + ' '.join(overrides) if overrides else ''}, "
          f"{config['scene']['num_steps']} steps per trajectory, linear solver {config['solver'].get('linear_solver', 'auto')}")
    for key, value in result.items():
        print(f"  {key:58s} {value:.3f}" if isinstance(value, float) else f"  {key:58s} {value}")
    return result


def bench_linear_solvers(nodes: tuple[int, int, int] = (10, 6, 6), frames: int = 12,
                         solvers: tuple[str, ...] = ("dense", "sparse")) -> dict:
    """The simulator's linear solvers on a tetrahedral block (`nodes` per axis over 1 x 0.6 x 0.6 m,
    E = 5 kPa, nu = 0.45, gravity, dt = 0.01 s) whose bottom third is clamped and whose top centre
    node is pulled up and sideways at 0.5 m/s, on one torch thread: per solver the median ms per
    frame, Newton iterations per frame, ms per Newton iteration, and ms of one factor + solve of the
    Newton matrix alone, over `frames` frames; and the largest position difference between solvers."""
    X, cells = box_tet_mesh((0, 0, 0), (1.0, 0.6, 0.6), [n - 1 for n in nodes])
    fixed = X[:, 2] < 0.2 + 1e-9  # the bottom third of the height
    pulled = int(np.argmin(((X - [0.5, 0.3, 0.6]) ** 2).sum(1)))
    fixed[pulled] = True
    velocity = torch.tensor([0.3, 0.0, 0.4], dtype=torch.float64)
    body = ElasticBody(torch.tensor(X), torch.tensor(cells), Material(5000.0, 0.45))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    result, final = {}, {}
    try:
        for solver in solvers:
            config = SolverConfig(dt=0.01, gravity=(0.0, 0.0, -9.81), linear_solver=solver)
            sim = Simulator(body, torch.tensor(fixed), config)
            x, v = body.X.clone(), torch.zeros_like(body.X)
            frame_ms, iterations, solve_ms = [], [], []
            for t in range(1, frames + 1):
                target = body.X.clone()
                target[pulled] += t * config.dt * velocity
                start = time.perf_counter()
                x, v, info = sim.step(x, v, fixed_positions=target)
                frame_ms.append(1e3 * (time.perf_counter() - start))
                iterations.append(info.newton_iterations)
                g, R = body.gradient(x)
                H = sim.linalg.stiffness(R) + sim.linalg.diag(sim.mass_dofs / config.dt**2)
                start = time.perf_counter()
                sim.linalg.solve(H, g.reshape(-1)[sim.free])
                solve_ms.append(1e3 * (time.perf_counter() - start))
            final[solver] = x
            result[solver] = {
                "ms/frame": statistics.median(frame_ms),
                "Newton iterations/frame": statistics.median(iterations),
                "ms/Newton iteration": statistics.median(f / i for f, i in zip(frame_ms, iterations)),
                "ms/factor+solve": statistics.median(solve_ms),
            }
    finally:
        torch.set_num_threads(threads)
    print(f"bench linear solvers: {len(X)} nodes, {len(cells)} tetrahedra, {int(sim.free.sum())} free dofs of "
          f"{sim.free.numel()}, {frames} frames, 1 torch thread (medians)")
    for solver, row in result.items():
        print(f"  {solver:7s}" + "".join(f"  {key} {value:8.2f}" for key, value in row.items()))
    if len(final) > 1:
        ref = final[solvers[0]]
        result["max position difference, m"] = max((x - ref).abs().max().item() for x in final.values())
        print(f"  max position difference between solvers: {result['max position difference, m']:.2e} m")
    return result


def bench_tangents(preset: str = "tissue_tiny", steps: int = 100, seeds: int = 3,
                   tangents: tuple[str, ...] = ("warped", "exact"), combinations: tuple[int, ...] | None = None,
                   first_seed: int = 1234, overrides: Sequence[str] = ()) -> dict:
    """Newton's tangents (`SolverConfig.tangent`) on a preset's scene, one torch thread: for every
    tangent, combination (default: all of the preset's) and seed first_seed .. first_seed + seeds - 1,
    one trajectory of `steps` frames made as generation makes it (simulate + observe), with its
    ms/frame, Newton iterations per frame (mean over frames 1.., max) and smallest det F of any
    element (`min_volume_ratio`: <= 0 means inverted) or the failure; and, per
    trajectory that the first tangent finished too, the largest position difference from it.
    Prints one line per trajectory and a summary per tangent and material; returns both.
    `overrides`: key=value overrides of the preset (e.g. another block or gripper path)."""
    base = load_config(preset, [f"scene.num_steps={steps}", *overrides])
    scene_module = SCENES[base["scene"]["name"]]
    sensor = DepthSensor(SensorConfig.from_dict(base["sensor"]))
    combos = range(scene_module.num_combinations(base["scene"])) if combinations is None else combinations
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    rows, finals = [], {}
    print(f"bench tangents: preset {preset!r}, {steps} frames per trajectory, 1 torch thread")
    try:
        for tangent in tangents:
            config = dict(base, solver=dict(base["solver"], tangent=tangent))
            for combination in combos:
                for seed in range(first_seed, first_seed + seeds):
                    row = {"tangent": tangent, "combination": combination, "seed": seed}
                    start = time.perf_counter()
                    try:
                        traj = scene_module.make_trajectory(config, combination, seed, sensor)
                    except SimulationError as error:
                        row["failure"] = str(error)
                        print(f"  {tangent:9s} combination {combination} seed {seed}: FAIL {error}")
                        rows.append(row)
                        continue
                    iterations = traj.diagnostics["newton_iterations"][1:]
                    row.update({"poissons_ratio": traj.poissons_ratio,
                                "ms/frame": 1e3 * (time.perf_counter() - start) / len(traj.positions),
                                "newton mean": float(iterations.mean()), "newton max": int(iterations.max()),
                                "min det F": min_volume_ratio(traj.positions, traj.rest_positions, traj.cells)})
                    finals[tangent, combination, seed] = traj.positions
                    reference = finals.get((tangents[0], combination, seed))
                    if reference is not None:
                        row["max position difference, m"] = float(np.abs(traj.positions - reference).max())
                    print(f"  {tangent:9s} combination {combination} seed {seed}: nu {row['poissons_ratio']:5.2f}  "
                          f"{row['ms/frame']:6.1f} ms/frame  Newton mean {row['newton mean']:5.2f} max "
                          f"{row['newton max']:3d}  min det F {row['min det F']:6.2f}" + (f"  vs {tangents[0]}: {row['max position difference, m']:.1e} m"
                                                      if reference is not None and tangent != tangents[0] else ""))
                    rows.append(row)
    finally:
        torch.set_num_threads(threads)
    # a failed trajectory has no Poisson's ratio of its own: it takes its combination's (from a row that
    # finished; NaN, its own summary line, if none did)
    nu_of = {r["combination"]: r["poissons_ratio"] for r in rows if "poissons_ratio" in r}
    for r in rows:
        r.setdefault("poissons_ratio", nu_of.get(r["combination"], float("nan")))
    summary = []
    for tangent in tangents:
        for nu in sorted({r["poissons_ratio"] for r in rows}, key=lambda v: (math.isnan(v), v)):
            same = [r for r in rows if r["tangent"] == tangent and (r["poissons_ratio"] == nu or
                                                                    math.isnan(nu) and math.isnan(r["poissons_ratio"]))]
            mine = [r for r in same if "failure" not in r]
            summary.append({
                "tangent": tangent, "poissons_ratio": nu, "finished": len(mine), "failed": len(same) - len(mine),
                "ms/frame (median)": statistics.median(r["ms/frame"] for r in mine) if mine else float("nan"),
                "newton mean": float(np.mean([r["newton mean"] for r in mine])) if mine else float("nan"),
                "newton max": max((r["newton max"] for r in mine), default=0),
                "min det F": min((r["min det F"] for r in mine), default=float("nan")),
                "max position difference, m": max((r.get("max position difference, m", 0.0) for r in mine), default=0.0),
            })
    print("  summary (per tangent and Poisson's ratio):")
    for row in summary:
        print(f"  {row['tangent']:9s} nu {row['poissons_ratio']:5.2f}  finished {row['finished']}  failed "
              f"{row['failed']}  ms/frame {row['ms/frame (median)']:6.1f}  Newton mean {row['newton mean']:5.2f}  "
              f"max {row['newton max']:3d}  min det F {row['min det F']:6.2f}  max |x - x_{tangents[0]}| {row['max position difference, m']:.1e} m")
    return {"rows": rows, "summary": summary}


def bench_contact(preset: str = "cavity", seeds: Sequence[int] = (11, 12), youngs_moduli: Sequence[float] | None = None,
                  poissons_ratios: Sequence[float] | None = None, overrides: Sequence[str] = ()) -> list[dict]:
    """The cavity's contact and materials, for choosing E (docs/cavity.md): every seed (one cavity
    shape and gripper path per seed) is simulated with every material, without cameras, on one torch
    thread. `youngs_moduli`: one E for all materials instead of the preset's; `poissons_ratios`: these
    nu instead of the preset's. Per trajectory: the RMS displacement from rest (all nodes and steps),
    the smallest element volume ratio (< 0: inverted), the deepest cavity node in a finger (the
    solver's contact tolerance bounds it) and the deepest finger vertex in the wall (between nodes),
    Newton iterations, the largest kinetic energy and seconds; per seed, the MSE between the
    trajectories of each pair of materials (what a model told the material can gain). Prints a table
    and returns its rows."""
    from .timing import NoSensor

    config = load_config(preset, list(overrides))
    scene = config["scene"]
    materials = [dict(m) for m in scene["materials"]]
    if poissons_ratios is not None:
        materials = [{"poissons_ratio": float(nu), "youngs_modulus": materials[min(i, len(materials) - 1)]["youngs_modulus"]}
                     for i, nu in enumerate(poissons_ratios)]
    if youngs_moduli is not None:
        materials = [dict(m, youngs_modulus=float(e)) for m in materials for e in youngs_moduli]
    scene["materials"] = materials
    module = SCENES[scene["name"]]
    rows = []
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        for seed in seeds:
            positions = {}
            for index, material in enumerate(materials):
                start = time.perf_counter()
                traj = module.make_trajectory(config, index, int(seed), NoSensor(3))
                seconds = time.perf_counter() - start
                d = traj.diagnostics
                positions[index] = traj.positions
                rows.append({"seed": int(seed), "nu": material["poissons_ratio"], "E": material["youngs_modulus"],
                             "rms_displacement": float(np.sqrt(((traj.positions - traj.rest_positions) ** 2).mean())),
                             "min_volume_ratio": min_volume_ratio(traj.positions, traj.rest_positions, traj.cells),
                             "node_penetration": float(d["max_penetration"].max()),
                             "finger_penetration": float(d.get("finger_penetration", np.zeros(1)).max()),
                             "newton": int(d["newton_iterations"].sum()), "kinetic_max": float(d["kinetic_energy"].max()),
                             "seconds": seconds})
            for a in range(len(materials)):
                for b in range(a + 1, len(materials)):
                    mse = float(((positions[a] - positions[b]) ** 2).mean())
                    print(f"  seed {seed}: material {a} ({materials[a]}) vs {b} ({materials[b]}): MSE {mse:.3e}")
                    rows.append({"seed": int(seed), "pair": f"{a}-{b}", "material_mse": mse})
    finally:
        torch.set_num_threads(threads)
    print(f"bench contact: preset {preset!r}, seeds {list(seeds)}")
    for row in rows:
        if "pair" not in row:
            print("  " + "  ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()))
    return rows
