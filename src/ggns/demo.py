"""The README's main job: generate the small plate dataset, train GGNS and MGN briefly through the
Lightning CLI (the same configs as `python -m ggns fit --config conf/plate/<model>.yaml`, with a
wall-clock budget), test both on the test split, and write a report under the output directory:

    report.md              the paper's metrics for both models (mean +- std over test trajectories)
    rollouts_<i>.png       ground truth vs. GGNS (point cloud every 5 steps) vs. MGN on test trajectory i
    plate_trajectories.png three training trajectories with their point clouds
    <model>/version_<n>/   TensorBoard logs, checkpoints, config.yaml, test_metrics.{md,json}
"""
from __future__ import annotations

import math
import time
from pathlib import Path

from .batch import TrajectoryBatch
from .cli import build_cli
from .config import CONF_DIR
from .data.module import SimulationDataModule
from .evaluation.pictures import rollout_picture
from .evaluation.schedules import EveryK
from .reports import markdown_table
from .viz import plot_trajectories, save_figure

MODELS = ("ggns", "mgn")


def train_and_test(name: str, output: Path, preset: str, minutes: float, test_trajectories: int = 9,
                   extra: list[str] = ()) -> dict:
    """Fit conf/plate/<name>.yaml for at most `minutes`, then test the checkpoint of its first
    ModelCheckpoint (the best full rollout: k=1 for GGNS, never for MGN) on the first
    `test_trajectories` test trajectories."""
    seconds = int(round(minutes * 60))
    args = ["--config", str(CONF_DIR / "plate" / f"{name}.yaml"), "--data.dataset", preset,
            "--trainer.max_time", f"00:{seconds // 3600:02d}:{seconds % 3600 // 60:02d}:{seconds % 60:02d}",
            "--trainer.max_epochs", "1000", "--trainer.check_val_every_n_epoch", "1",
            "--trainer.limit_val_batches", "8",
            # the test: the first `test_trajectories` of the split (the first 9 of a balanced
            # plate split are 3 shapes x 3 materials), all at once
            "--data.max_eval_trajectories", str(test_trajectories), "--data.eval_batch_size", str(test_trajectories),
            "--trainer.enable_progress_bar", "false",
            "--trainer.logger.init_args.save_dir", str(output), "--trainer.logger.init_args.name", name, *extra]
    cli = build_cli(args, run=False)
    # half an epoch per "epoch": validation, rollout evaluation and checkpoint selection then
    # happen every ~1-2 min on plate_small, so a short budget still ends on a selected checkpoint
    data = cli.datamodule
    windows = sum(t.num_steps - cli.model.window for t in data.trajectories("train"))
    cli.trainer.limit_train_batches = max(1, math.ceil(windows / data.batch_size) // 2)
    start = time.perf_counter()
    cli.trainer.fit(cli.model, datamodule=cli.datamodule)
    fit_seconds = time.perf_counter() - start
    callback = cli.trainer.checkpoint_callback
    ckpt = callback.best_model_path or callback.last_model_path or None
    cli.trainer.test(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt)
    return {"name": name, "module": cli.model, "datamodule": cli.datamodule, "results": cli.model.test_results,
            "epochs": cli.trainer.current_epoch, "steps": cli.trainer.global_step, "fit_seconds": fit_seconds,
            "checkpoint": ckpt, "log_dir": cli.trainer.log_dir}


def _fmt(s: dict | None) -> str:
    return "n/a" if s is None else f"{s['mean']:.3e} ± {s['std']:.1e}"


def write_report(runs: list[dict], path: Path, figures: list[Path], preset: str, minutes: float,
                 test_trajectories: int) -> Path:
    names = [r["name"] for r in runs]
    metrics = list(dict.fromkeys(m for r in runs for m in r["results"]))
    lines = [
        "# Main job report: GGNS vs. MGN on the small Deformable Plate dataset", "",
        f"Data preset `{preset}`; each model trained for at most {minutes:g} min of wall-clock time on this "
        f"machine (paper-size models, far shorter than the paper's training), then tested on the first "
        f"{test_trajectories} test trajectories with the checkpoint that had the best validation rollout MSE "
        "(GGNS: a point cloud every step; MGN: none; the table below names it). Values: mean ± std over test trajectories; "
        "MSEs in squared task-space units; `k<K>`: a point cloud every K steps, `never`: none after the initial "
        "state. MGN never sees point clouds, so only its `never` rollout exists.", "",
        markdown_table(["metric", *names], [[m, *(_fmt(r["results"].get(m)) for r in runs)] for m in metrics]),
    ]
    lines += ["", markdown_table(["model", "epochs", "optimizer steps", "fit time (s)", "checkpoint", "logs"],
                        [[r["name"], r["epochs"], r["steps"], f"{r['fit_seconds']:.0f}", f"`{r['checkpoint']}`",
                          f"`{r['log_dir']}`"] for r in runs])]
    lines += ["", *(f"![rollouts]({f.name})" for f in figures), "",
              "TensorBoard: `.venv/bin/tensorboard --logdir " + str(path.parent) + "`", ""]
    path.write_text("\n".join(lines))
    return path


def rollout_pictures(runs: list[dict], path: Path, trajectories: int = 2) -> list[Path]:
    """Ground truth vs. each model's rollout on the first test trajectories, one figure row per model."""
    dm = runs[0]["datamodule"]
    trajs = dm.trajectories("test")[:trajectories]
    models = {r["name"].upper(): r["module"].eval() for r in runs}
    figures = [rollout_picture(TrajectoryBatch.from_trajectories([traj]), traj.collider_faces, models, EveryK(5),
                               title=f"test trajectory, nu={traj.poissons_ratio:g} (green: point clouds given to GGNS)")
               for traj in trajs]
    return [save_figure(fig, path.with_name(f"{path.stem}_{i}{path.suffix}")) for i, fig in enumerate(figures)]


def run_demo(output: str | Path = "lightning_logs/demo", preset: str = "plate_small", minutes: float = 4.0,
             models: tuple[str, ...] = MODELS, test_trajectories: int = 9, extra: list[str] = ()) -> Path:
    output = Path(output)
    start = time.perf_counter()
    data = SimulationDataModule(preset)
    data.prepare_data()  # generates the splits that are missing
    print(f"wrote {plot_trajectories(data.trajectories('train')[:3], output / 'plate_trajectories.png')}")
    runs = [train_and_test(name, output, preset, minutes, test_trajectories, extra) for name in models]
    figures = rollout_pictures(runs, output / "rollouts.png")
    report = write_report(runs, output / "report.md", figures, preset, minutes, test_trajectories)
    print(f"\nmain job done in {time.perf_counter() - start:.0f} s")
    print(f"report: {report}\nrollout pictures: {', '.join(map(str, figures))}\nlogs: {output}/<model>/version_<n>/")
    return report
