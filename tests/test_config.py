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


def test_experiment_presets_are_found_by_name_after_the_shipped_ones_and_no_name_is_taken_twice():
    """The experiments' sweeps and learning files (experiments/<experiment>/<kind>/) resolve by name in a
    checkout as conf/'s do; conf/ comes first; a name is one preset per kind, so a name never picks one of two."""
    from ggns.config import EXPERIMENTS_DIR, preset_files, resolve_preset

    for kind in ("sweeps", "learning"):
        names = [p.stem for p in preset_files(kind)]
        assert len(names) == len(set(names)), kind
        assert any(p.is_relative_to(EXPERIMENTS_DIR) for p in preset_files(kind))
    assert resolve_preset("plate_cpu_partition", "sweeps") == EXPERIMENTS_DIR / "plate_cpu" / "sweeps" / "plate_cpu_partition.yaml"
    assert resolve_preset("plate_cpu", "sweeps") == CONF_DIR / "sweeps" / "plate_cpu.yaml"  # shipped
    assert resolve_preset("plate_cpu", "learning") == EXPERIMENTS_DIR / "plate_cpu" / "learning" / "plate_cpu.yaml"
    assert not list(CONF_DIR.glob("*/plate_cpu_partition.yaml"))  # not shipped in the package
    with pytest.raises(FileNotFoundError, match="experiments.*known: .*plate_cpu_partition"):
        resolve_preset("plate_cpu_partitio", "sweeps")
