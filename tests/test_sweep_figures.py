import math

import matplotlib.pyplot as plt
import numpy as np
import pytest

from ggns.sweeps.aggregate import normalized_benefit
from ggns.sweeps.figures import (benefit_curve, draw_benefit_curve, draw_schedule_bars, iou_bars,
                                      m_plus_10_bars, rollout_mse_bars, write_figures)

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
KS = ("k1", "k2", "k5", "k10", "never")


def stat(mean, std=0.1, seeds=3):
    return {"mean": mean, "std": std, "seeds": seeds}


def make_table(std=0.1, seeds=3, with_mgn=True, with_iou=True):
    ggns = {}
    for i, s in enumerate(KS):
        ggns[f"rollout_mse_{s}"] = stat(1e-3 * (i + 1), std * 1e-3, seeds)
        if with_iou:
            ggns[f"rollout_iou_{s}"] = stat(0.95 - 0.02 * i, std * 0.01, seeds)
    ggns["m10_mse"] = stat(2e-4, std * 1e-4, seeds)
    ggns["one_step_mse"] = stat(1e-6, std * 1e-7, seeds)
    table = {"ggns": ggns}
    if with_mgn:
        mgn = {"rollout_mse_never": stat(1e-2, std * 1e-3, seeds), "m10_mse": stat(5e-3, std * 1e-3, seeds)}
        if with_iou:
            mgn["rollout_iou_never"] = stat(0.7, std * 0.01, seeds)
        table["mgn"] = mgn
    return table


def assert_png(path):
    assert path.is_file()
    assert path.read_bytes()[:8] == PNG_MAGIC


@pytest.mark.parametrize("plot", [rollout_mse_bars, m_plus_10_bars, iou_bars, benefit_curve])
@pytest.mark.parametrize("std", [0.1, math.nan])
def test_each_figure_writes_png(tmp_path, plot, std):
    table = make_table(std=std, seeds=3 if std == std else 1)
    before = plt.get_fignums()  # figures another test in this process left open are not this one's
    path = plot(table, tmp_path / "sub" / "fig.png")
    assert path == tmp_path / "sub" / "fig.png"
    assert_png(path)
    assert plt.get_fignums() == before  # closed


def test_write_figures_full_set(tmp_path):
    paths = write_figures(make_table(), tmp_path)
    assert {p.name for p in paths} == {"rollout_mse.png", "m_plus_10.png", "rollout_iou.png",
                                       "normalized_benefit.png"}
    for p in paths:
        assert p.parent == tmp_path
        assert_png(p)


def test_write_figures_skips_benefit_without_mgn_and_iou_when_absent(tmp_path):
    paths = write_figures(make_table(with_mgn=False, with_iou=False), tmp_path)
    assert {p.name for p in paths} == {"rollout_mse.png", "m_plus_10.png"}
    assert not (tmp_path / "normalized_benefit.png").exists()


def test_write_figures_skips_benefit_when_a_k_is_missing(tmp_path):
    table = make_table()
    del table["ggns"]["rollout_mse_k5"]
    names = {p.name for p in write_figures(table, tmp_path)}
    assert names == {"rollout_mse.png", "m_plus_10.png", "rollout_iou.png"}


def test_write_figures_skips_benefit_when_ggns_k1_is_not_below_mgn(tmp_path):
    table = make_table()
    table["ggns"]["rollout_mse_k1"]["mean"] = table["mgn"]["rollout_mse_never"]["mean"] * 2
    (tmp_path / "normalized_benefit.png").write_bytes(b"stale")  # from an earlier aggregation
    names = {p.name for p in write_figures(table, tmp_path)}
    assert "normalized_benefit.png" not in names and "rollout_mse.png" in names
    assert not (tmp_path / "normalized_benefit.png").exists()


def test_write_figures_one_seed(tmp_path):
    table = make_table(std=math.nan, seeds=1)
    assert len(write_figures(table, tmp_path)) == 4


def test_benefit_curve_data_matches_normalized_benefit():
    table = make_table()
    fig, ax = plt.subplots()
    try:
        returned = draw_benefit_curve(ax, table)
        expected = normalized_benefit(table)
        assert returned == expected
        (line,) = [l for l in ax.lines if l.get_label() == "ggns vs mgn"]
        np.testing.assert_allclose(line.get_xdata(), [1, 2, 5, 10])
        np.testing.assert_allclose(line.get_ydata(), [expected[k] for k in (1, 2, 5, 10)])
        assert line.get_ydata()[0] == pytest.approx(1.0)
        (zero,) = [l for l in ax.lines if l is not line]
        np.testing.assert_allclose(zero.get_ydata(), [0, 0])
    finally:
        plt.close(fig)


def test_schedule_bars_heights_and_error_bars():
    table = make_table()
    table["mgn"]["rollout_mse_never"]["std"] = math.nan  # one bar without an error bar
    fig, ax = plt.subplots()
    try:
        draw_schedule_bars(ax, table, "rollout_mse_")
        heights = sorted(p.get_height() for p in ax.patches)
        expected = sorted([table["ggns"][f"rollout_mse_{s}"]["mean"] for s in KS]
                          + [table["mgn"]["rollout_mse_never"]["mean"]])
        np.testing.assert_allclose(heights, expected)
        assert len(ax.containers) - 6 == 5  # 6 bar containers, 5 error bars (NaN std: none)
    finally:
        plt.close(fig)


def test_missing_metrics_raise_in_single_figures(tmp_path):
    before = plt.get_fignums()
    with pytest.raises(ValueError):
        iou_bars(make_table(with_iou=False), tmp_path / "iou.png")
    with pytest.raises(ValueError):
        benefit_curve(make_table(with_mgn=False), tmp_path / "b.png")
    assert plt.get_fignums() == before


def test_summarize_writes_and_links_figures(tmp_path):
    import json

    from ggns.sweeps.summary import summarize
    from ggns.sweeps.sweep import runs_of

    table = make_table()
    sweep = {"output": str(tmp_path / "out"), "seeds": [0, 1],
             "models": {"ggns": {"config": "unused.yaml"}, "mgn": {"config": "unused.yaml"}}}
    for run in runs_of(sweep):
        run.test_dir.mkdir(parents=True)
        metrics = {m: {"mean": s["mean"] * (1 + 0.1 * run.seed), "std": 0.0, "count": 2}
                   for m, s in table[run.model].items()}
        run.metrics_path.write_text(json.dumps(metrics))
    summary = summarize(sweep, log=lambda *_: None).read_text()
    for name in ("rollout_mse", "m_plus_10", "rollout_iou", "normalized_benefit"):
        assert f"![{name}]({name}.png)" in summary
        assert_png(tmp_path / "out" / f"{name}.png")
