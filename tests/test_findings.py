"""The paper's plate findings checked on hand-made aggregated tables (ggns.sweeps.findings)."""
from __future__ import annotations

import math

import pytest

from ggns.sweeps.findings import as_ggns, check_findings, check_targets, findings_markdown


def stat(mean, std=0.0):
    return {"mean": mean, "std": std, "seeds": 3}


def paper_like():
    """A table in which every finding holds."""
    ggns = {f"rollout_mse_k{k}": stat(v, 0.1 * v) for k, v in ((1, 1e-4), (2, 2e-4), (5, 5e-4), (10, 9e-4))}
    ggns["m10_mse"], ggns["m10_pooled_mse"] = stat(1e-5), stat(4e-6)
    lstm = {f"rollout_mse_k{k}": stat(1.1 * ggns[f"rollout_mse_k{k}"]["mean"], 1e-5) for k in (1, 2, 5, 10)}
    return {"ggns": ggns, "ggns_lstm": lstm,
            "mgn_m": {"rollout_mse_never": stat(1e-3), "m10_mse": stat(2e-5), "m10_pooled_mse": stat(5e-6)},
            "mgn": {"rollout_mse_never": stat(5e-3), "m10_mse": stat(3e-5), "m10_pooled_mse": stat(6e-6)}}


def verdicts(table):
    return [f.holds for f in check_findings(table)]


def test_all_findings_hold_on_a_paper_like_table():
    findings = check_findings(paper_like())
    assert [f.holds for f in findings] == [True] * 5
    assert "25.00x" in findings[1].evidence  # 5e-3 / 2e-4
    assert "k=1: 1.000" in findings[3].evidence
    text = findings_markdown(findings)
    assert text.count("| holds |") == 5


def test_each_finding_can_fail():
    t = paper_like()
    t["ggns"]["rollout_mse_k2"] = stat(2e-3)  # above MGN(M): order broken, ratio 2.5x, benefit still falls
    assert verdicts(t)[:2] == [False, False]
    t = paper_like()
    t["mgn_m"]["m10_mse"] = stat(5e-6)  # below GGNS at S_m+10 only: the paper's m+10 is the pooled one
    assert verdicts(t)[2] is True
    t["mgn_m"]["m10_pooled_mse"] = stat(3e-6)  # MGN(M) below GGNS on the paper's m+10
    assert verdicts(t)[2] is False
    t = paper_like()
    t["ggns"]["rollout_mse_k10"] = stat(4e-4)  # benefit at k = 10 above k = 5
    assert verdicts(t)[3] is False
    t = paper_like()
    t["ggns_lstm"]["rollout_mse_k5"] = stat(1e-4, 1e-6)  # LSTM well below GGNS at k = 5
    finding = check_findings(t)[4]
    assert finding.holds is False and "k = [5]" in finding.evidence


def test_no_benefit_to_normalize_when_ggns_k1_is_worse_than_mgn():
    t = paper_like()
    for k, v in ((1, 6e-3), (2, 7e-3), (5, 8e-3), (10, 9e-3)):  # benefit(k) > 1 and rising: meaningless
        t["ggns"][f"rollout_mse_k{k}"] = stat(v)
    finding = check_findings(t)[3]
    assert finding.holds is False and "no benefit to normalize" in finding.evidence


def test_lstm_inside_the_seed_spread_is_not_better():
    t = paper_like()
    t["ggns_lstm"]["rollout_mse_k2"] = stat(0.95 * 2e-4, 1e-6)  # 5 % lower, GGNS std is 10 %
    assert check_findings(t)[4].holds is True
    t["ggns"]["rollout_mse_k2"]["std"] = math.nan  # one seed: no spread, so lower is better
    t["ggns_lstm"]["rollout_mse_k2"]["std"] = math.nan
    assert check_findings(t)[4].holds is False


def test_missing_models_are_not_checked_never_held():
    t = {"ggns": paper_like()["ggns"]}
    findings = check_findings(t)
    assert [f.holds for f in findings] == [None] * 5
    assert "missing" in findings[0].evidence and "not checked" in findings_markdown(findings)


def test_targets_hold_and_fail():
    t = paper_like()
    t["ggns"]["rollout_mse_never"] = stat(2e-3)
    t["static"] = {}
    for model, value in (("ggns", 1e-6), ("ggns_lstm", 2e-6), ("mgn_m", 1e-6), ("mgn", 2e-6), ("static", 1e-5)):
        t[model]["one_step_mse"] = stat(value)
    t["alpha_shapes"] = {"rollout_iou_k1": stat(0.9)}
    targets = check_targets(t)
    assert [f.holds for f in targets] == [True] * 6
    assert "GGNS 4e-06, MGN(M) 5e-06" in targets[5].evidence
    assert "10.00x" in targets[3].evidence and "GGNS 1e-05, MGN(M) 2e-05" in targets[4].evidence
    assert "ggns 0.1" in targets[0].evidence and "static 1" not in targets[0].evidence  # the reference is no model
    assert "50.00x" in targets[2].evidence  # 5e-3 / 1e-4
    assert findings_markdown(targets, head="target").startswith("| target |")
    t["mgn"]["one_step_mse"] = stat(3e-6)  # 0.3x no motion
    t["ggns"]["rollout_mse_never"] = stat(8e-4)  # below k = 10
    t["mgn"]["rollout_mse_never"] = stat(9e-4)  # 9x GGNS k = 1
    t["mgn_m"]["rollout_mse_never"] = stat(2.9e-4)  # 2.9x GGNS k = 1
    t["mgn_m"]["m10_mse"] = stat(1e-5)  # equal to GGNS's: not below
    t["mgn_m"]["m10_pooled_mse"] = stat(3e-6)  # below GGNS's
    assert [f.holds for f in check_targets(t)] == [False] * 6
    del t["static"]
    assert check_targets(t)[0].holds is None
    del t["ggns"]["m10_pooled_mse"]
    assert check_targets(t)[5].holds is None
    assert [f.holds for f in check_targets({})] == [None] * 6


def test_a_variant_of_ggns_is_judged_in_its_place():
    t = paper_like()
    variant = {name: stat(2 * v["mean"], v["std"]) for name, v in t["ggns"].items()}  # twice GGNS's error
    variant["rollout_mse_k1"] = stat(5e-4)  # 2x MGN(M) (1e-3): not 3x below it
    t["ggns_id"] = variant
    judged = as_ggns(t, "ggns_id")
    assert judged["ggns"] is variant and "ggns_id" not in judged and judged["ggns (the sweep's)"] is t["ggns"]
    assert check_targets(judged)[3].holds is False and "2.00x" in check_targets(judged)[3].evidence
    assert check_targets(t)[3].holds is True  # the table itself is unchanged
    with pytest.raises(KeyError, match="'ggns_pt' not in the table"):
        as_ggns(t, "ggns_pt")
