"""The README's demo (`make demo`, `python -m ggns demo [--task tissue]`), set by conf/demo/<task>.yaml:

1. generate the task's small data preset on this machine (numbers are made here, never copied);
2. evaluate the pretrained GGNS (a point cloud every k = 1, 2, 5, 10 steps, never), MGN and MGN(M)
   (`ggns.pretrained`) on its test trajectories with the paper's metrics;
3. pictures of one test trajectory: truth vs GGNS vs MGN at several steps (point clouds over the GGNS
   panels), an animation of the same rollouts, and the error over time of every model and k;
4. train GGNS from scratch for a few minutes through the Lightning CLI with CPU-tuned settings, and plot
   its validation curve against the pretrained GGNS's (its manifest) and the pretrained MGN's level;
5. write report.md beside the pictures, with the paper's figures next to ours, and print where it all went.
"""
from __future__ import annotations

import math
import os
import time
import warnings
from pathlib import Path

import matplotlib
import numpy as np

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from tqdm import tqdm  # noqa: E402

from ..batch import TrajectoryBatch  # noqa: E402
from .lightning import build_cli  # noqa: E402
from ..config import (CONF_DIR, LIGHTNING_KEYS, command_line, config_file, load_layered, old_form_error,  # noqa: E402
                     resolve_preset)
from ..data.module import SimulationDataModule  # noqa: E402
from ..evaluation.evaluate import MetricTable  # noqa: E402
from ..evaluation.pictures import error_curves, rollout_animation, rollout_picture, rollout_series  # noqa: E402
from ..evaluation.schedules import Never, parse_schedule  # noqa: E402
from ..sweeps.curves import read_scalars  # noqa: E402
from ..sweeps.paper import LABELS, paper_figures  # noqa: E402
from ..pretrained import budget_text, check_data, load  # noqa: E402
from ..reports import markdown_table, write_json, write_text  # noqa: E402
from ..viz import plot_error_over_time, save_figure  # noqa: E402

TASKS = ("plate", "tissue")


def load_demo(task: str) -> dict:
    if task not in TASKS:
        raise ValueError(f"unknown demo task {task!r}; expected one of {TASKS}")
    spec = load_layered(resolve_preset(task, "demo"), "demo")
    train = spec["train"]
    if "args" in train:
        raise old_form_error(f"{CONF_DIR / 'demo' / task}.yaml: train: `args`", train["args"] or [])
    unknown = sorted({str(k).split(".")[0] for k in train.get("overrides") or {}} - set(LIGHTNING_KEYS))
    if unknown:
        raise ValueError(f"{CONF_DIR / 'demo' / task}.yaml: train: `overrides` has keys {unknown}, which are not "
                         f"Lightning's (known: {list(LIGHTNING_KEYS)})")
    spec.setdefault("paper", paper_figures(task))  # the paper's test figures, for the report
    return spec


def evaluate_pretrained(spec: dict, data: SimulationDataModule) -> tuple[dict, dict, TrajectoryBatch]:
    """({key: model}, {key: {metric: {mean, std, count}}}, the test batch) for every pretrained entry."""
    models = {key: load(name) for key, name in spec["pretrained"].items()}
    for key, name in spec["pretrained"].items():
        check_data(name, data.config, data.dim, source=f"data preset {spec['data']!r}")
    trajectories = data.trajectories("test")[:spec["test_trajectories"]]
    batch = TrajectoryBatch.from_trajectories(trajectories)
    schedules = [parse_schedule(s) for s in spec["schedules"]]
    results = {}
    for key, model in tqdm(models.items(), desc=f"evaluate on {len(trajectories)} test trajectories", unit="model"):
        table = MetricTable()
        table.add(model.evaluate(batch, schedules=schedules if model.uses_points else [Never()], m_plus_10=True,
                                 iou=True))
        results[key] = table.summary()
    return models, results, batch


def _fmt(value) -> str:
    return "-" if value is None else f"{value:.2e}"


def results_table(spec: dict, results: dict) -> str:
    """Ours (mean ± std over the test trajectories) beside the paper's, one row per metric."""
    keys = list(results)
    metrics = list(dict.fromkeys(m for r in results.values() for m in r))
    rows = []
    for metric in metrics:
        ours = [f"{results[k][metric]['mean']:.2e} ± {results[k][metric]['std']:.1e}" if metric in results[k] else "-"
                for k in keys]
        paper = spec.get("paper", {}).get(metric, {})
        rows.append([f"`{metric}`", *ours, *(_fmt(paper.get(k)) for k in keys)])
    return markdown_table(["metric", *(f"{LABELS[k]} (ours)" for k in keys), *(f"{LABELS[k]} (paper)" for k in keys)],
                          rows)


def claim(results: dict, budgets: dict | None = None) -> tuple[float | None, str]:
    """GGNS k=1 against MGN (full rollout MSE): (ratio, one sentence naming each model's training budget,
    `budgets`: key -> its words, `ggns.pretrained.budget_text`, when given)."""
    budgets = budgets or {}

    def given(key: str) -> str:
        return f", trained {budgets[key]}" if budgets.get(key) not in (None, "-") else ""

    ggns = results.get("ggns", {}).get("rollout_mse_k1", {}).get("mean")
    mgn = results.get("mgn", {}).get("rollout_mse_never", {}).get("mean")
    mgn_m = results.get("mgn_m", {}).get("rollout_mse_never", {}).get("mean")
    if ggns is None or mgn is None:
        return None, "the claim cannot be checked: GGNS k=1 or MGN missing"
    ratio = mgn / ggns
    text = (f"GGNS with a point cloud every step (k=1) is **{_relation(ggns, mgn)} MGN** "
            f"({ggns:.2e}{given('ggns')}, against {mgn:.2e}{given('mgn')}): the claim (at least 10x below) "
            f"**{'holds' if ratio >= 10 else 'fails'}** here")
    if mgn_m is not None:
        text += (f"; against MGN(M), which is told the material, GGNS k=1 is {_relation(ggns, mgn_m)} it "
                 f"({mgn_m:.2e}{given('mgn_m')})")
    return ratio, text + "."


def _relation(a: float, b: float) -> str:
    """"3.2x below" / "1.4x above": a against b."""
    return f"{b / a:.1f}x below" if a <= b else f"{a / b:.1f}x above"


def pictures(spec: dict, models: dict, data: SimulationDataModule, output: Path) -> list[Path]:
    """Rollout figure, animation and error-over-time plot of test trajectory `picture_trajectory`."""
    trajectory = data.trajectories("test")[spec["picture_trajectory"]]
    batch = TrajectoryBatch.from_trajectories([trajectory])
    shown = {LABELS[k]: models[k] for k in ("ggns", "mgn") if k in models}
    schedule = parse_schedule(spec["picture_schedule"])
    title = f"test trajectory {spec['picture_trajectory']}, nu={trajectory.poissons_ratio:g}"
    with tqdm(total=3, desc="pictures", unit="picture") as bar:
        series = rollout_series(batch, shown, schedule)
        figure = save_figure(rollout_picture(batch, trajectory.collider_faces, shown, schedule, num_frames=5,
                                             title=title + " (green: point clouds given to GGNS)", series=series),
                             output / "rollouts.png")
        bar.update()
        animation = rollout_animation(batch, trajectory.collider_faces, shown, schedule, output / "rollout.gif",
                                      title=title, series=series)
        bar.update()
        curves = error_curves(batch, {LABELS[k]: m for k, m in models.items()}, spec["schedules"])
        errors = plot_error_over_time(curves, output / "error_over_time.png", title=title)
        bar.update()
    return [figure, animation, errors]


def train_arguments(spec: dict, output: Path, minutes: float) -> list[str]:
    """The Lightning CLI arguments of the from-scratch fit: `train.config`, then `train.configs` stacked after
    it, the demo's data and validation trajectories, then `train.overrides` (conf/demo's CPU-tuned settings),
    the budget, a progress bar, and the log directory."""
    train = spec["train"]
    seconds = int(round(minutes * 60))
    files = [str(config_file(path)) for path in [train["config"], *(train.get("configs") or [])]]
    return [*(part for path in files for part in ("--config", path)), "--data.dataset", spec["data"],
            "--data.max_eval_trajectories", str(train["val_trajectories"]),
            "--data.eval_batch_size", str(train["val_trajectories"]), *command_line(train.get("overrides") or {}),
            "--trainer.max_time", f"00:{seconds // 3600:02d}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}",
            "--trainer.enable_progress_bar", "true", "--trainer.enable_model_summary", "false",
            "--trainer.logger.init_args.save_dir", str(output), "--trainer.logger.init_args.name", "ggns_from_scratch"]


def train_from_scratch(spec: dict, output: Path, minutes: float) -> dict:
    """Fit GGNS from nothing for `minutes` through the Lightning CLI (`train_arguments`: conf/demo's
    CPU-tuned settings, progress bar on); returns its log directory, steps, seconds and validation curve."""
    args = train_arguments(spec, output, minutes)
    with warnings.catch_warnings():  # LightningCLI warns that `python -m ggns demo`'s own argv is not its args
        warnings.filterwarnings("ignore", message=".*LightningCLI's args parameter.*")
        cli = build_cli(args, run=False)
    start = time.perf_counter()
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    log_dir = Path(cli.trainer.log_dir)
    scalars = read_scalars(log_dir)
    steps, walls, values = scalars.get("val/rollout_mse_k1", ([], [], []))
    first = min((float(w.min()) for _, w, _ in scalars.values() if len(w)), default=0.0)
    return {"log_dir": log_dir, "steps": cli.trainer.global_step, "seconds": time.perf_counter() - start,
            "curve": [(float(s), float(w) - first, float(v)) for s, w, v in zip(steps, walls, values)]}


def mgn_validation_level(models: dict, data: SimulationDataModule, count: int) -> float:
    """The pretrained MGN's full rollout MSE on the validation trajectories the from-scratch GGNS is scored on."""
    batch = TrajectoryBatch.from_trajectories(data.trajectories("val")[:count])
    return float(models["mgn"].evaluate(batch, schedules=[Never()], m_plus_10=False, iou=False)
                 ["rollout_mse_never"].mean())


def plot_learning(scratch: dict, pretrained_curve: list, mgn_level: float, path: Path, task: str) -> Path:
    """Validation rollout MSE (k=1) against optimizer steps: GGNS from scratch, the pretrained GGNS's
    training run, and the pretrained MGN's level and a tenth of it."""
    fig, ax = plt.subplots(figsize=(7.5, 4.5), layout="constrained")
    if pretrained_curve:
        s, v = zip(*pretrained_curve)
        ax.plot(s, v, "o-", color="tab:blue", alpha=0.6, label="pretrained GGNS's training run (its manifest)")
    if scratch["curve"]:
        s, _, v = zip(*scratch["curve"])
        ax.plot(s, v, "o-", color="tab:green", label=f"GGNS from scratch here ({scratch['seconds'] / 60:.1f} min)")
    ax.axhline(mgn_level, color="tab:red", ls="--", label="pretrained MGN (no point clouds)")
    ax.axhline(mgn_level / 10, color="tab:red", ls=":", label="MGN / 10 (the claim)")
    ax.set(xscale="log", yscale="log", xlabel="optimizer steps", ylabel="validation rollout MSE, k=1",
           title=f"{task}: what longer training buys")
    ax.legend(fontsize=8)
    return save_figure(fig, path)


def time_to_claim(scratch: dict, mgn_level: float) -> tuple[float, float] | None:
    """(step, seconds) of the from-scratch run's first validation at least 10x below MGN, or None."""
    for step, seconds, value in scratch["curve"]:
        if value <= mgn_level / 10:
            return step, seconds
    return None


def run_demo(task: str = "plate", output: str | Path = "lightning_logs/demo", minutes: float | None = None,
             test_trajectories: int | None = None, data: str | None = None, train: bool = True,
             spec: dict | None = None) -> Path:
    """The demo (module docstring) with conf/demo/<task>.yaml, or `spec` in its layout."""
    start = time.perf_counter()
    spec = load_demo(task) if spec is None else spec
    if test_trajectories is not None:
        spec["test_trajectories"] = test_trajectories
    if data is not None:
        spec["data"] = data
    minutes = spec["train"]["minutes"] if minutes is None else minutes
    output = Path(output) / task
    module = SimulationDataModule(spec["data"])
    print(f"[1/4] data: {spec['data']} -> {module.data_dir} (generated once, then reused)")
    module.prepare_data()
    print(f"[2/4] pretrained {', '.join(spec['pretrained'].values())} on the test split")
    models, results, _ = evaluate_pretrained(spec, module)
    ratio, sentence = claim(results, {key: budget_text(model.manifest) for key, model in models.items()})
    print("      " + sentence.replace("**", ""))
    print("[3/4] pictures")
    figures = pictures(spec, models, module, output)
    scratch = None
    if train and minutes > 0:
        print(f"[4/4] GGNS from scratch for {minutes:g} min")
        scratch = train_from_scratch(spec, output, minutes)
        level = mgn_validation_level(models, module, spec["train"]["val_trajectories"])
        manifest_curve = models["ggns"].manifest["validation"].get("val/rollout_mse_k1", [])
        figures.append(plot_learning(scratch, manifest_curve, level, output / "learning.png", task))
        scratch["mgn_level"], scratch["claim_at"] = level, time_to_claim(scratch, level)
    report = write_report(spec, task, results, sentence, figures, scratch, models, output,
                          time.perf_counter() - start)
    write_json(output / "results.json", {"task": task, "results": results, "ratio_mgn_over_ggns_k1": ratio})
    print(f"\ndemo done in {time.perf_counter() - start:.0f} s")
    print(f"report:   {report}\npictures: {', '.join(map(str, figures))}\nmetrics:  {output / 'results.json'}")
    if scratch:
        print(f"training logs: {scratch['log_dir']} (tensorboard --logdir {output})")
    return report


def write_report(spec: dict, task: str, results: dict, sentence: str, figures: list[Path], scratch: dict | None,
                 models: dict, output: Path, seconds: float) -> Path:
    count = next(iter(next(iter(results.values())).values()))["count"]
    title = f"# The shipped {task} simulators (GGNS, MGN, MGN(M)) on {count} test trajectories"
    lines = [title + (", and a GGNS trained from scratch" if scratch else ""), "",
             f"Made on this machine ({os.cpu_count()} CPU cores) in {seconds / 60:.1f} min: {count} test trajectories of "
             f"the `{spec['data']}` preset generated here, the shipped simulators "
             f"({', '.join(f'`{n}`' for n in spec['pretrained'].values())}) rolled out from the initial state.", "",
             sentence, "",
             "Full rollout MSE (`rollout_mse_k<K>`: a point cloud every K steps; `never`: none after S_0), the paper's "
             "m+10-step MSE (`m10_mse` at S_m+10; `m10_pooled_mse` over every step of each rollout, the paper's reading), "
             "the one-step MSE and the IoU of the predicted mesh, mean ± std over the test "
             "trajectories, in squared task-space units; MGN never sees point clouds. The paper's columns are its "
             "test figures (full rollouts read off its bar charts, `-` where it gives none).", "",
             results_table(spec, results), ""]
    lines += ["| simulator | trained | optimizer steps of its fit | file from step | parameters | "
              "manifest test (same trajectories) |",
              "|---|---|---|---|---|---|"]
    for key, model in models.items():
        m = model.manifest
        family = m["source"]["family"]
        metric = f"rollout_mse_{family}"
        lines.append(f"| `{m['name']}` | {m['trained_by']['fit_started']} on `{m['data']['preset']}` | "
                     f"{budget_text(m)} | "
                     f"{m['source']['global_step']} | {m['parameters']} | {metric} "
                     f"{m['test']['metrics'][metric]['mean']:.3e} on {m['test']['trajectories']} |")
    lines += ["", *(f"![{p.stem}]({p.name})" for p in figures if p.suffix == ".png" and p.stem != "learning"),
              "", "Animation: [rollout.gif](rollout.gif)", ""]
    if scratch:
        at = scratch["claim_at"]
        lines += ["## GGNS from scratch", "",
                  f"{scratch['steps']} optimizer steps in {scratch['seconds'] / 60:.1f} min (validation included) with "
                  f"`conf/demo/{task}.yaml`'s CPU settings; logs in `{scratch['log_dir']}`. On the first "
                  f"{spec['train']['val_trajectories']} validation trajectories the pretrained MGN's full rollout MSE is "
                  f"{scratch['mgn_level']:.2e}; the from-scratch GGNS's best k=1 is "
                  f"{min((v for _, _, v in scratch['curve']), default=math.nan):.2e}. "
                  + (f"It was first 10x below MGN at step {at[0]:.0f}, {at[1] / 60:.1f} min after the fit began."
                     if at else "It did not get 10x below MGN in this budget (the pretrained GGNS's curve shows "
                                "what longer training buys)."), "", "![learning](learning.png)", ""]
    return write_text(output / "report.md", "\n".join(lines))


def run_online(task: str = "tissue", output: str | Path = "lightning_logs/demo", spec: dict | None = None,
               trajectory: int = 0, every: int = 2, latency: int = 1, noise: float = 1.0, seed: int = 0) -> Path:
    """The online loop on one test trajectory (`ggns demo --online`): the trajectory stands in for the world,
    its virtual cameras' masked depth frames of every `every`-th tick arrive `latency` ticks late with the
    axial depth noise of `noise` times the Kinect's (`SensorConfig.axial_noise`, metres), and the shipped GGNS
    tracks it online (`ggns.online.OnlineSimulator`, the frames through `DepthProcessing`) beside the blind
    GGNS, MGN and MGN(M), and beside MGN corrected by a registration to each frame (`ggns.online.Registration`,
    the task's settings of conf/online/registration.yaml). Writes online.png (the mesh MSE against the true state at each tick), online.json
    (the per-tick errors and the settings) and online.md into <output>/<task>/; returns online.md."""
    from ..bench.online import camera_frames
    from ..bench.online_study import METRES_PER_UNIT, registration_settings, track
    from ..config import load_config
    from ..online import DepthProcessing
    from ..sensors.camera import sensor_flaws

    if every < 1 or latency < 0 or noise < 0:
        raise ValueError(f"need every >= 1, latency >= 0 and noise >= 0; got {every}, {latency}, {noise}")
    spec = load_demo(task) if spec is None else spec
    output = Path(output) / task
    module = SimulationDataModule(spec["data"])
    module.prepare_data()
    worlds = module.trajectories("test")
    if not 0 <= trajectory < len(worlds):
        raise IndexError(f"test trajectory {trajectory} not among the {len(worlds)} of {spec['data']}")
    world, config = worlds[trajectory], load_config(spec["data"])
    models = {key: load(name).eval() for key, name in spec["pretrained"].items()}
    for key, model in models.items():
        check_data(spec["pretrained"][key], config, dim=world.dim, source=f"data preset {spec['data']!r}")
    print(f"[online] {spec['data']} test trajectory {trajectory}: a frame every {every} ticks, {latency} late, "
          f"axial noise {noise:g}x the Kinect's")
    flaws = sensor_flaws("axial", METRES_PER_UNIT[task], noise_scale=noise)
    frames = camera_frames(config, world, flaws, np.random.default_rng(seed))
    depth = DepthProcessing.from_sensor_config(config["sensor"])
    curves = {f"GGNS, a frame every {every} ticks, {latency} late": track(models["ggns"], world, frames, every,
                                                                           latency, depth)[0],
              f"MGN + registration, the same frames": track(models["mgn"], world, frames, every, latency, depth,
                                                            registration_settings(task))[0],
              "GGNS blind": track(models["ggns"], world, None, 1, 0, depth)[0],
              "MGN (blind)": track(models["mgn"], world, None, 1, 0, depth)[0],
              "MGN(M) (blind)": track(models["mgn_m"], world, None, 1, 0, depth)[0]}
    figure = plot_error_over_time({k: np.concatenate([[0.0], v]) for k, v in curves.items()}, output / "online.png",
                                  title=f"{task}: online tracking of test trajectory {trajectory}")
    means = {k: float(v.mean()) for k, v in curves.items()}
    grounded = next(iter(means))
    write_json(output / "online.json", {"task": task, "data": spec["data"], "trajectory": trajectory, "every": every,
                                        "latency": latency, "noise": noise, "seed": seed,
                                        "checkpoints": {k: m.manifest["sha256"] for k, m in models.items()},
                                        "tracking_mse": means, "per_tick_mse": {k: v.tolist() for k, v in curves.items()}})
    rows = [[name, f"{value:.3e}", "-" if name == grounded else _relation(means[grounded], value)]
            for name, value in means.items()]
    text = "\n".join([f"# Online tracking: {task}, test trajectory {trajectory}", "",
                      f"The shipped GGNS stepped tick by tick, fed the virtual cameras' masked depth frames of every "
                      f"{every}-th tick {latency} tick(s) late with {noise:g}x the Kinect's axial noise, beside the "
                      "blind models and MGN registered to the same frames (docs/online.md: which to use). Tracking "
                      "error: the mean over ticks of the mesh MSE against the true state.", "",
                      markdown_table(["run", "tracking MSE", "grounded GGNS is"], rows), "",
                      f"![error over time]({figure.name})", ""])
    report = write_text(output / "online.md", text)
    print(text)
    return report
