"""`python -m ggns paper` (ggns.sweeps.paper): sweep summaries in the paper's layout, the paper's figures beside."""
from __future__ import annotations

import pytest
import yaml

from ggns.__main__ import main
from ggns.sweeps.paper import COLUMNS, PAPER_FIGURES, TASKS, paper_figures, paper_table, read_summary

SUMMARY = """model,metric,mean,std,seeds
ggns,rollout_mse_k1,1.0e-4,1.0e-5,3
ggns,rollout_mse_k2,4.0e-4,2.0e-5,3
ggns,m10_mse,5.0e-4,5.0e-5,3
ggns,m10_pooled_mse,2.0e-4,2.0e-5,3
ggns,one_step_mse,1.0e-5,1.0e-6,3
mgn_m,rollout_mse_never,2.0e-4,1.0e-5,3
mgn_m,m10_mse,1.0e-4,1.0e-5,3
mgn_m,m10_pooled_mse,5.0e-5,5.0e-6,3
mgn,rollout_mse_never,3.0e-3,1.0e-4,3
static,one_step_mse,4.0e-5,nan,1
static,rollout_mse_never,2.0e-2,nan,1
alpha_shapes,generated_mesh_iou_k1,0.9,nan,1
"""


def test_the_paper_figures_file_is_complete_and_consistent():
    figures = yaml.safe_load(PAPER_FIGURES.read_text())
    assert sorted(figures) == sorted(TASKS)
    for task, metrics in figures.items():
        for metric, models in metrics.items():
            if metric == "figure":
                continue
            assert metric in COLUMNS, (task, metric)
            for model, value in models.items():
                assert model in ("ggns", "ggns_lstm", "mgn", "mgn_m") and value["mean"] > 0, (task, metric, model)
                low, high = value.get("range", (value["mean"], value["mean"]))
                assert low <= value["mean"] <= high, (task, metric, model)
    plate = paper_figures("plate")
    assert plate["rollout_mse_k1"]["ggns"] == pytest.approx(1.856e-5) and plate["m10_pooled_mse"]["mgn"] == pytest.approx(2.82684e-3)
    assert "m10_mse" not in plate  # the paper's m+10 is pooled over each rollout (the file's header)
    with pytest.raises(ValueError, match="unknown task 'moon'"):
        paper_figures("moon")


def test_the_table_puts_ours_beside_the_paper_and_computes_the_claims_ratios(tmp_path):
    path = tmp_path / "summary.csv"
    path.write_text(SUMMARY)
    ours = read_summary(path)
    assert ours["ggns"]["one_step_ratio"][0] == pytest.approx(0.25)  # against predicting no motion (static)
    text = paper_table("plate", {"run": path})
    rows = {line.split(" | ")[0].lstrip("| "): line for line in text.splitlines() if line.startswith("| ")}
    assert "1.00e-04 ± 1.0e-05" in rows["GGNS (3 seeds)"] and "0.250 ± 0.025" in rows["GGNS (3 seeds)"]
    assert "paper: GGNS" in rows and "1.86e-05" in rows["paper: GGNS"] and "2.91e-05" in rows["paper: GGNS"]
    assert not any("alpha" in row for row in rows)  # a baseline of generated-mesh metrics only
    assert "| MGN(M) never / GGNS k=1 (paper: > 1) | 2.00x | 11.38x |" in text
    assert "| MGN(M) m+10 pooled / GGNS m+10 pooled (paper: > 1) | 0.25x | 3.67x |" in text
    assert "| MGN(M) m+10 at S_m+10 / GGNS's | 0.20x | - |" in text  # the paper reports no such number
    assert "| MGN never / GGNS k=1 | 30.00x | 296.61x |" in text


def test_the_command_writes_the_table_and_refuses_what_is_not_a_summary(tmp_path, capsys):
    path = tmp_path / "summary.csv"
    path.write_text(SUMMARY)
    main(["paper", "--task", "tissue", "--summary", f"a={path}", "--summary", f"b={path}",
          "--output", str(tmp_path / "out" / "tissue.md")])
    text = (tmp_path / "out" / "tissue.md").read_text()
    assert "a: GGNS (3 seeds)" in text and "b: GGNS (3 seeds)" in text and "paper: GGNS" in text
    assert text.count("static") == 1  # one no-motion row for both summaries
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    with pytest.raises(SystemExit) as exit_info:
        main(["paper", "--task", "plate", "--summary", f"x={bad}"])
    assert exit_info.value.code == 2 and "not a sweep summary" in capsys.readouterr().err


def test_summaries_of_disjoint_seeds_pool_into_one_mean_and_sample_std(tmp_path):
    one, two = tmp_path / "seed0.csv", tmp_path / "seed12.csv"
    one.write_text("model,metric,mean,std,seeds\nggns,rollout_mse_k1,1.0,nan,1\nstatic,one_step_mse,4.0,nan,1\n")
    two.write_text("model,metric,mean,std,seeds\nggns,rollout_mse_k1,4.0,1.4142135623730951,2\nstatic,one_step_mse,4.0,nan,1\n")
    pooled = read_summary(f"{one},{two}")
    mean, std, seeds = pooled["ggns"]["rollout_mse_k1"]
    assert seeds == 3 and mean == pytest.approx(3.0)  # seeds 1, 3, 5
    assert std == pytest.approx(2.0)  # the sample std of (1, 3, 5)
    assert pooled["static"]["one_step_mse"] == (4.0, pytest.approx(float("nan"), nan_ok=True), 1)  # not pooled
