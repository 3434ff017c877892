"""A finished sweep's results (`python -m ggns sweep --aggregate-only`, and the end of every sweep): the
non-learned baselines on the sweep's test trajectories (`run_baselines`) and the summary tables, figures,
findings and training curves of all runs beside them (`summarize`)."""
from __future__ import annotations

from pathlib import Path

from ..reports import markdown_table, write_json, write_text
from ..data import DEFAULT_DATASET
from ..evaluation.selection import checkpoint_info
from .aggregate import RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown
from .curves import LATE_STEPS, markdown_rows, plot_curves, read_scalars, variant_row
from .findings import as_ggns, check_findings, check_targets, findings_markdown
from .sweep import Run, runs_of


def _run_result(run: Run) -> RunResult:
    """A finished run's test metrics, with its generated-mesh baseline metrics when computed."""
    from ..baselines import GENERATED_MESH_FILE

    result = load_run(run.metrics_path, run.model, run.seed)
    extra = run.test_dir / GENERATED_MESH_FILE
    if extra.is_file():
        result.metrics.update(load_run(extra, run.model, run.seed).metrics)
    return result


# summary sections: (title, metric-name prefixes), in this order; other metrics go last
SECTIONS = (("Full-rollout MSE (point cloud every k steps)", ("rollout_mse_",)),
            ("One-step and m+10-step MSE", ("one_step_mse", "m10_mse")),
            ("Rollout IoU (true initial mesh)", ("rollout_iou_",)),
            ("Rollout IoU from a mesh generated from the first point cloud", ("generated_mesh_iou_",)))


def _sections(table) -> list[str]:
    metrics = list(dict.fromkeys(m for per_metric in table.values() for m in per_metric))
    lines, used = [], set()
    for title, prefixes in SECTIONS + (("Other metrics", None),):
        chosen = [m for m in metrics if m not in used and (prefixes is None or m.startswith(prefixes))]
        rows = {model: per_metric for model, per_metric in table.items() if any(m in per_metric for m in chosen)}
        if chosen and rows:
            used.update(chosen)
            lines += [f"## {title}", "", to_markdown(rows, chosen)]
    return lines


def _steps_logged(scalars: dict) -> int | None:
    """The largest TensorBoard step of any scalar of a fit (`curves.read_scalars` of its event files;
    its training length, to within `log_every_n_steps`; validation is logged at the step it ran), or None."""
    # read_scalars counts optimizer steps completed (TensorBoard step + 1)
    return int(max(steps.max() for steps, _, _ in scalars.values())) - 1 if scalars else None


def _training_markdown(runs: list[Run], results: list[RunResult], curves: list[dict]) -> str:
    """Per run and metric family: the tested checkpoint (its step / epoch, what it was selected on,
    any fallback) and the largest step the fit logged (`curves`: each run's `read_scalars`). Runs
    tested before per-family selection recorded no checkpoints; theirs are found as they were chosen
    then (`Run.checkpoints`)."""
    rows = []
    for run, result, scalars in zip(runs, results, curves):
        logged = _steps_logged(scalars)
        logged = "-" if logged is None else str(logged)
        checkpoints = result.checkpoints
        if not checkpoints:
            try:
                checkpoints = {family: {**checkpoint_info(sel.checkpoint), "note": "tested before per-family "
                                        "selection (one checkpoint for every family)"}
                               for family, sel in run.checkpoints().items()}
            except FileNotFoundError:  # checkpoints removed after testing
                rows.append((run.model, run.seed, "-", "(removed)", "-", "-", "-", logged))
                continue
        for family, info in checkpoints.items():
            selected = info.get("selected_on") or "-"
            if info.get("score") is not None:
                selected += f" = {info['score']:.4g}"
            rows.append((run.model, run.seed, family, info["name"], f"{info['global_step']} / {info['epoch']}", selected,
                         info.get("note") or "", logged))
    return markdown_table(["model", "seed", "family", "tested checkpoint", "its step / epoch", "selected on", "note",
                           "largest logged step of the fit"], rows) + "\n"


def _learning_markdown(runs: list[Run], scalars: list[dict], output: Path) -> list[str]:
    """The learning-curve table of every run (`curves.variant_row` of its `read_scalars`, in
    `scalars`) and the curves against optimizer steps (learning_curves.png)."""
    curves = {f"{run.model} seed {run.seed}": run_scalars for run, run_scalars in zip(runs, scalars)}
    rows = [variant_row(name, [], scalars) for name, scalars in curves.items()]
    groups = {f"{run.model} seed {run.seed}": (run.model, i) for run in runs
              for i, seed in enumerate(sorted({r.seed for r in runs})) if seed == run.seed}
    figure = plot_curves(curves, output / "learning_curves.png", "steps", title="run", groups=groups)
    return ["## Learning curves of each run", "",
            "Read from each fit's TensorBoard events: optimizer steps and training seconds (wall seconds "
            "since the first event where a fit logged no `time/train_seconds`, validation included), the "
            "validation metrics at the last validation / the best one, the slope of log10 rollout (or m+10) MSE per "
            "1000 steps over the second half of the validations (negative: still falling), and the training "
            f"loss of graphs with / without a point cloud over the last {LATE_STEPS} steps.", "",
            markdown_rows(rows, label="run", change=False), f"![{figure.stem}]({figure.name})", ""]


def summarize(sweep: dict, log=print) -> Path:
    """Aggregate the finished runs (and the baselines computed by `run_baselines`) into
    <output>/summary.md and summary.csv (mean +- std over seeds; the normalized benefit of
    point clouds when the sweep has `ggns` and `mgn`) plus figures."""
    from ..baselines import ROWS as BASELINE_ROWS
    from .figures import write_figures

    finished = [r for r in runs_of(sweep) if r.finished]
    if not finished:
        raise FileNotFoundError(f"{sweep['output']}: no finished run to aggregate")
    output = Path(sweep["output"])
    results = [_run_result(r) for r in finished]
    scalars = [read_scalars(r.fit_dir) if r.fit_dir.is_dir() else {} for r in finished]  # each fit's events, read once
    for row in BASELINE_ROWS:
        path = output / row / "test_metrics.json"
        if path.is_file():
            results.append(load_run(path, row, 0))
    table = aggregate(results)
    to_csv(table, output / "summary.csv")
    lines = ["# Sweep summary", "", f"{len(finished)} of {len(runs_of(sweep))} runs finished; mean ± std over seeds "
             "(a single value where there is one seed or a deterministic baseline).", ""] + _sections(table)
    if "ggns" in table and "mgn" in table:
        try:
            benefit = normalized_benefit(table)
            lines += ["## Normalized benefit of point clouds (1 at k = 1, 0 at MGN)", "",
                      markdown_table(["k", *benefit], [["benefit", *(f"{v:.3f}" for v in benefit.values())]])]
        except ValueError as error:
            lines += ["", f"Normalized benefit not computed: {error}"]
    lines += ["", "## The paper's findings on this sweep", "", findings_markdown(check_findings(table))]
    lines += ["## The project's targets on this sweep", "",
              "Every model's one-step MSE against predicting no motion (the `static` row), GGNS's rollout "
              "MSE over the point-cloud schedules, GGNS k=1 against MGN (ggns.sweeps.findings).", "",
              findings_markdown(check_targets(table), head="target")]
    for model in sweep.get("findings_ggns", []):  # variants of GGNS, each judged in GGNS's place
        if model in table:
            stand_in = as_ggns(table, model)
            lines += [f"## The paper's findings and the project's targets with `{model}` as GGNS", "",
                      findings_markdown(check_findings(stand_in)),
                      findings_markdown(check_targets(stand_in), head="target")]
    lines += ["## Training of each run and the checkpoint each metric family was tested with", "",
              _training_markdown(finished, results[:len(finished)], scalars)]
    lines += _learning_markdown(finished, scalars, output)
    lines += [f"![{figure.stem}]({figure.name})" for figure in write_figures(table, output)]
    path = output / "summary.md"
    write_text(path, "\n".join(lines) + "\n")
    log(f"wrote {path} and {output / 'summary.csv'}")
    return path


# ---- the baselines -----------------------------------------------------------------------------
def _test_trajectories(spec: dict):
    from ..data.module import SimulationDataModule

    module = SimulationDataModule(spec.get("dataset", DEFAULT_DATASET), data_dir=spec.get("data_dir"),
                                  max_eval_trajectories=spec.get("max_trajectories"), generate_missing=False)
    return module.trajectories("test")


def baseline_spec(sweep: dict) -> dict:
    """The sweep's `baselines` section, checked ({} when absent)."""
    spec = sweep.get("baselines") or {}
    unknown = set(spec) - {"dataset", "data_dir", "max_trajectories", "alpha_shapes", "static", "initial_mesh"}
    if unknown:
        raise ValueError(f"sweep baselines: unknown keys {sorted(unknown)}")
    models = spec.get("initial_mesh") or []
    if isinstance(models, str):
        models = [models]
    missing = [m for m in models if m not in sweep["models"]]
    if missing:
        raise ValueError(f"sweep baselines: initial_mesh names models {missing} that the sweep does not have "
                         f"({sorted(sweep['models'])})")
    return {**spec, "initial_mesh": list(models)}


def run_baselines(sweep: dict, log=print) -> list[Path]:
    """Compute the missing baseline results of the sweep (see the module docstring): Alpha Shapes
    and the static reference once, and the generated-mesh rollouts for every finished run of the `initial_mesh` models.
    Returns the files written."""
    from ..baselines import ALPHA_SHAPES, GENERATED_MESH_FILE, STATIC

    spec = baseline_spec(sweep)
    written: list[Path] = []
    trajectories = None
    for row in (ALPHA_SHAPES, STATIC):
        path = Path(sweep["output"]) / row / "test_metrics.json"
        if spec.get(row) and not path.is_file():
            from ..baselines import scores  # here: torch and PyG, seconds to import

            compute = scores.alpha_shapes_metrics if row == ALPHA_SHAPES else scores.static_metrics
            trajectories = trajectories if trajectories is not None else _test_trajectories(spec)
            log(f"baseline {row} on {len(trajectories)} test trajectories")
            write_json(path, compute(trajectories))
            written.append(path)
    for run in runs_of(sweep):
        path = run.test_dir / GENERATED_MESH_FILE
        if run.model not in spec["initial_mesh"] or not run.finished or path.is_file():
            continue
        trajectories = trajectories if trajectories is not None else _test_trajectories(spec)
        log(f"baseline initial mesh generation: {run.model} seed {run.seed}")
        metrics = {}
        for part in run.test_parts():  # each schedule with the checkpoint selected on its family
            if part.schedules:
                from ..baselines.scores import generated_mesh_metrics
                from ..models.loading import load_simulator  # here: Lightning, seconds to import

                model = load_simulator(part.checkpoint, map_location="cpu")
                metrics.update(generated_mesh_metrics(model, trajectories, part.schedules))
        write_json(path, metrics)
        written.append(path)
    return written
