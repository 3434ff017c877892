"""Presets and overrides (ggns.config): a preset over its base and a key=value override may change
keys, never add one; a typo is an error naming the key and the nearest valid ones."""
from __future__ import annotations

import pytest

from ggns.config import CONF_DIR, UnknownKeyError, load_config, unknown_keys


def test_every_shipped_preset_loads():
    for kind in ("data", "graphs", "geometry"):
        for path in sorted((CONF_DIR / kind).glob("*.yaml")):
            assert load_config(path.stem, kind=kind), path


def test_overrides_change_known_keys_and_refuse_new_ones():
    config = load_config("plate_tiny", ["scene.grid_nodes=5", "splits.train=4"])
    assert config["scene"]["grid_nodes"] == 5 and config["splits"]["train"] == 4
    assert config["scene"]["num_steps"] == 8  # plate_tiny over its base plate
    with pytest.raises(UnknownKeyError, match=r"scene\.gird_nodes \(did you mean scene\.grid_nodes\?\)"):
        load_config("plate_tiny", ["scene.gird_nodes=5"])
    with pytest.raises(UnknownKeyError, match=r"known at this level"):
        load_config("plate_tiny", ["scene.collider.zzz=1"])


def test_a_preset_cannot_add_a_key_to_its_base(tmp_path):
    (tmp_path / "base.yaml").write_text("scene: {grid_nodes: 9, num_steps: 50}\nseed: 0\n")
    (tmp_path / "child.yaml").write_text("base: base.yaml\nscene: {num_step: 8}\n")
    with pytest.raises(UnknownKeyError, match=r"unknown key\(s\) in .*child\.yaml \(over its base base\.yaml\): scene\.num_step "
                                              r"\(did you mean scene\.num_steps\?\)"):
        load_config(tmp_path / "child.yaml")


def test_unknown_keys_compares_mappings_only():
    known = {"a": {"b": 1, "c": [1, 2]}, "d": 2}
    assert unknown_keys(known, {"a": {"c": [3]}, "d": {"x": 1}}) == []  # a list or a scalar replaced whole
    assert unknown_keys(known, {"a": {"bb": 1}}) == ["a.bb (did you mean a.b?)"]
