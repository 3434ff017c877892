import csv
import json
import math

import pytest

from ggns.sweeps import NoBenefitError, RunResult, aggregate, load_run, normalized_benefit, to_csv, to_markdown


def _runs():
    return [
        RunResult("ggns", 0, {"rollout_mse_k1": 1.0, "rollout_mse_k2": 3.0, "rollout_mse_k5": 5.0,
                              "rollout_mse_k10": 9.0, "one_step_mse": 1.0}),
        RunResult("ggns", 1, {"rollout_mse_k1": 3.0, "rollout_mse_k2": 5.0, "rollout_mse_k5": 7.0,
                              "rollout_mse_k10": 11.0, "one_step_mse": 2.0}),
        RunResult("ggns", 2, {"rollout_mse_k1": 2.0, "rollout_mse_k2": 4.0, "rollout_mse_k5": 6.0,
                              "rollout_mse_k10": 10.0, "one_step_mse": 3.0}),
        RunResult("mgn", 0, {"rollout_mse_never": 9.0, "one_step_mse": 0.5}),
        RunResult("mgn", 1, {"rollout_mse_never": 11.0, "one_step_mse": 0.5}),
    ]


def test_mean_and_sample_std():
    table = aggregate(_runs())
    s = table["ggns"]["one_step_mse"]
    assert s["mean"] == pytest.approx(2.0) and s["std"] == pytest.approx(1.0) and s["seeds"] == 3
    assert table["mgn"]["rollout_mse_never"]["mean"] == pytest.approx(10.0)
    assert table["mgn"]["rollout_mse_never"]["std"] == pytest.approx(math.sqrt(2.0))
    assert table["mgn"]["one_step_mse"]["std"] == 0.0
    assert "rollout_mse_k1" not in table["mgn"]


def test_single_seed_std_is_nan():
    table = aggregate([RunResult("m", 0, {"x": 4.0})])
    assert table["m"]["x"]["mean"] == 4.0 and math.isnan(table["m"]["x"]["std"])


def test_normalized_benefit():
    # seed means: MGN never 10, GGNS k1 2, k2 4, k5 6, k10 10
    b = normalized_benefit(aggregate(_runs()))
    assert b[1] == pytest.approx(1.0)
    assert b[2] == pytest.approx(0.75)   # (10 - 4) / (10 - 2)
    assert b[5] == pytest.approx(0.5)    # (10 - 6) / (10 - 2)
    assert b[10] == pytest.approx(0.0)   # at the MGN level
    assert list(b) == [1, 2, 5, 10]


def test_normalized_benefit_errors():
    table = aggregate(_runs())
    with pytest.raises(ValueError, match="mgn2"):
        normalized_benefit(table, mgn_model="mgn2")
    with pytest.raises(ValueError, match="rollout_mse_k3"):
        normalized_benefit(table, ks=(1, 3))
    flat = aggregate([RunResult("ggns", 0, {"rollout_mse_k1": 5.0}), RunResult("mgn", 0, {"rollout_mse_never": 5.0})])
    with pytest.raises(NoBenefitError, match="no benefit to normalize"):
        normalized_benefit(flat)


def test_no_normalized_benefit_when_ggns_k1_is_worse_than_mgn():
    # the ratio would be (10 - k) / (10 - 12): 1 at k = 1, then above 1 and rising, which means nothing
    worse = aggregate([RunResult("ggns", 0, {"rollout_mse_k1": 12.0, "rollout_mse_k2": 13.0}),
                       RunResult("mgn", 0, {"rollout_mse_never": 10.0})])
    with pytest.raises(NoBenefitError, match="rollout_mse_k1 12 is not below mgn rollout_mse_never 10"):
        normalized_benefit(worse, ks=(1, 2))
    assert issubclass(NoBenefitError, ValueError)


def test_markdown_cells():
    md = to_markdown(aggregate(_runs()), metrics=["one_step_mse", "rollout_mse_never"])
    lines = md.strip().splitlines()
    assert lines[0] == "| model | one_step_mse | rollout_mse_never |"
    assert lines[2] == "| ggns | 2 ± 1 | - |"
    assert lines[3] == "| mgn | 0.5 ± 0 | 10 ± 1.414 |"
    assert "rollout_mse_k1" in to_markdown(aggregate(_runs()))


def test_csv_round_trip(tmp_path):
    table = aggregate(_runs() + [RunResult("solo", 0, {"one_step_mse": 0.1})])
    path = tmp_path / "results.csv"
    to_csv(table, path)
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == sum(len(v) for v in table.values())
    back = {}
    for r in rows:
        back.setdefault(r["model"], {})[r["metric"]] = {"mean": float(r["mean"]), "std": float(r["std"]),
                                                         "seeds": int(r["seeds"])}
    assert math.isnan(back["solo"]["one_step_mse"].pop("std"))
    table["solo"]["one_step_mse"].pop("std")
    assert back == table


def test_nan_metric_raises():
    runs = _runs() + [RunResult("mgn", 2, {"rollout_mse_never": float("nan")})]
    with pytest.raises(ValueError, match=r"'mgn'.*seed 2.*rollout_mse_never"):
        aggregate(runs)
    with pytest.raises(ValueError, match="non-finite"):
        aggregate([RunResult("m", 0, {"x": float("inf")})])


def test_duplicate_run_raises():
    with pytest.raises(ValueError, match=r"duplicate.*'ggns'.*seed 1"):
        aggregate(_runs() + [RunResult("ggns", 1, {"one_step_mse": 1.0})])


def test_load_run(tmp_path):
    path = tmp_path / "test_metrics.json"
    path.write_text(json.dumps({"one_step_mse": {"mean": 0.25, "std": 0.1, "count": 4},
                                "rollout_mse_never": {"mean": 3.0, "std": 1.0, "count": 4}}))
    run = load_run(path, "mgn", 7)
    assert run == RunResult("mgn", 7, {"one_step_mse": 0.25, "rollout_mse_never": 3.0})


def test_load_run_errors(tmp_path):
    bad = tmp_path / "bad_metrics.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad_metrics.json"):
        load_run(bad, "mgn", 0)
    no_mean = tmp_path / "no_mean.json"
    no_mean.write_text(json.dumps({"x": {"std": 1.0}}))
    with pytest.raises(ValueError, match="no_mean.json"):
        load_run(no_mean, "mgn", 0)
    with pytest.raises(FileNotFoundError, match="missing.json"):
        load_run(tmp_path / "missing.json", "mgn", 0)
