"""experiments/plate_cpu/scripts/equal_steps_report.py on TensorBoard logs written as a sweep's fits write them
(real event files): the grounding ratio only at steps both models validated, a run partway through
reported as unfinished, the raw files and the figure written."""
from __future__ import annotations

import csv
import importlib.util
from pathlib import Path

import pytest
from torch.utils.tensorboard import SummaryWriter

SCRIPT = Path(__file__).resolve().parents[1] / "experiments" / "plate_cpu" / "scripts" / "equal_steps_report.py"


def _load():
    spec = importlib.util.spec_from_file_location("equal_steps_report", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _log(directory: Path, validations: dict[int, dict[str, float]], seconds_per_step: float) -> None:
    writer = SummaryWriter(str(directory))
    for step, values in validations.items():  # Lightning logs after n steps at TensorBoard step n - 1
        for tag, value in values.items():
            writer.add_scalar(tag, value, step - 1)
        writer.add_scalar("time/train_seconds", step * seconds_per_step, step - 1)
    writer.close()


def test_the_report_pairs_equal_steps_and_marks_unfinished_runs(tmp_path):
    sweep = tmp_path / "sweep"
    _log(sweep / "ggns" / "seed_0", {4000: {"val/rollout_mse_k1": 1e-4, "val/rollout_mse_never": 3e-3},
                                      8000: {"val/rollout_mse_k1": 5e-5, "val/rollout_mse_never": 2e-3}}, 0.1)
    _log(sweep / "mgn" / "seed_0", {4000: {"val/rollout_mse_never": 4e-3}, 8000: {"val/rollout_mse_never": 3e-3},
                                     12000: {"val/rollout_mse_never": 2.5e-3}}, 0.05)
    (sweep / "mgn" / "seed_0_test").mkdir()
    (sweep / "mgn" / "seed_0_test" / "test_metrics.json").write_text("{}")
    report = _load().main(["--sweep", str(sweep), "--output", str(tmp_path / "out"), "--baselines", "mgn", "mgn_m",
                           "--max-steps", "12000"])
    out = tmp_path / "out"
    ratios = list(csv.DictReader((out / "ratios.csv").open()))
    assert [(int(r["step"]), r["baseline"]) for r in ratios] == [(4000, "mgn"), (8000, "mgn")]  # 12000: GGNS not there
    assert [float(r["ratio"]) for r in ratios] == pytest.approx([40.0, 60.0])
    status = {r["model"]: r for r in csv.DictReader((out / "status.csv").open())}
    assert set(status) == {"ggns", "mgn"}  # mgn_m has no logs
    assert (status["ggns"]["optimizer_steps"], status["ggns"]["finished"], status["ggns"]["tested"]) == ("8000", "False", "False")
    assert (status["mgn"]["optimizer_steps"], status["mgn"]["finished"], status["mgn"]["tested"]) == ("12000", "True", "True")
    assert float(status["ggns"]["steps_per_train_second"]) == pytest.approx(10.0)
    assert (out / "curves_steps.png").stat().st_size > 0
    assert "no (running or stopped)" in report.read_text()
    rows = list(csv.DictReader((out / "validations.csv").open()))
    assert len(rows) == 5


def test_no_logs_is_an_error_naming_the_folder(tmp_path):
    with pytest.raises(SystemExit, match="no run of"):
        _load().main(["--sweep", str(tmp_path), "--output", str(tmp_path / "out")])


def test_a_run_without_logs_is_kept_from_an_earlier_report(tmp_path):
    """GGNS's logs gone, its earlier raw files kept: the new baseline is paired with GGNS's kept validations."""
    sweep, earlier = tmp_path / "sweep", tmp_path / "earlier"
    _log(sweep / "ggns" / "seed_0", {4000: {"val/rollout_mse_k1": 1e-4}, 8000: {"val/rollout_mse_k1": 5e-5}}, 0.1)
    module = _load()
    module.main(["--sweep", str(sweep), "--output", str(earlier)])
    (sweep / "ggns" / "seed_0").rename(tmp_path / "gone")
    _log(sweep / "mgn" / "seed_0", {4000: {"val/rollout_mse_never": 4e-3}, 8000: {"val/rollout_mse_never": 3e-3}}, 0.05)
    out = tmp_path / "out"
    report = module.main(["--sweep", str(sweep), "--output", str(out), "--baselines", "mgn", "--earlier", str(earlier)])
    ratios = list(csv.DictReader((out / "ratios.csv").open()))
    assert [float(r["ratio"]) for r in ratios] == pytest.approx([40.0, 60.0])
    status = {r["model"]: r for r in csv.DictReader((out / "status.csv").open())}
    assert (status["ggns"]["optimizer_steps"], status["mgn"]["optimizer_steps"]) == ("8000", "8000")
    assert "Kept from the earlier report's raw files (no logs under the sweep): ggns." in report.read_text()
    with pytest.raises(SystemExit, match="no validations.csv"):
        module.main(["--sweep", str(sweep), "--output", str(out), "--earlier", str(tmp_path / "nothing")])


def test_the_test_ratios_and_the_power_law_of_ggns_k1(tmp_path):
    """k=1 logged as 1e-2 * step^-0.5 from step 20,000 on (and a point before it the fit must leave out): the
    fitted exponent is -0.5 and the law reaches 1e-5 at step 1e6; the test ratio is the baseline's never over
    GGNS's k=1 from their test_metrics.json."""
    import json

    sweep = tmp_path / "sweep"
    law = {s: {"val/rollout_mse_k1": 1e-2 * s ** -0.5, "val/rollout_mse_never": 1e-3} for s in (20000, 40000, 80000)}
    _log(sweep / "ggns" / "seed_0", {4000: {"val/rollout_mse_k1": 1.0, "val/rollout_mse_never": 1.0}, **law}, 0.1)
    _log(sweep / "mgn" / "seed_0", {80000: {"val/rollout_mse_never": 3e-3}}, 0.1)
    for model, metrics in {"ggns": {"rollout_mse_k1": 4e-5, "rollout_mse_never": 3e-3},
                           "mgn": {"rollout_mse_never": 2e-3, "one_step_mse": 1e-6}}.items():
        (sweep / model / "seed_0_test").mkdir()
        (sweep / model / "seed_0_test" / "test_metrics.json").write_text(json.dumps(
            {**{k: {"mean": v, "std": v / 10, "count": 27} for k, v in metrics.items()}, "checkpoints": {"k1": "x"}}))
    report = _load().main(["--sweep", str(sweep), "--output", str(tmp_path / "out"), "--baselines", "mgn",
                           "--fit-from", "20000", "--target", "1e-5"])
    out = tmp_path / "out"
    (fit,) = list(csv.DictReader((out / "fit.csv").open()))
    assert (int(fit["points"]), int(fit["fit_to"])) == (3, 80000)
    assert float(fit["exponent"]) == pytest.approx(-0.5, rel=1e-4)
    assert int(fit["steps_to_target"]) == pytest.approx(1_000_000, rel=1e-3)
    tests = {(r["model"], r["metric"]): float(r["mean"]) for r in csv.DictReader((out / "tests.csv").open())}
    assert tests[("mgn", "ratio_never_to_ggns_k1")] == pytest.approx(50.0)
    assert ("ggns", "checkpoints") not in tests
    assert "reaches 1e-05 at step" in report.read_text()
