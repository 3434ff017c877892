"""Presets and overrides (ggns.config): a preset over its base and a key=value override may change
keys, never add one; a typo is an error naming the key and the nearest valid ones."""
from __future__ import annotations

from pathlib import Path

import pytest

from ggns.config import CONF_DIR, UnknownKeyError, load_config, unknown_keys

ROOT = Path(__file__).resolve().parents[1]


def test_every_preset_loads_and_the_experiments_keep_theirs():
    """Every data, graph and geometry preset loads by name, the shipped ones and those beside the experiments
    that alone use them (experiments/<experiment>/{data,graphs}/: not shipped in the package)."""
    from ggns.config import preset_files

    for kind in ("data", "graphs", "geometry"):
        for path in preset_files(kind):
            assert load_config(path.stem, kind=kind), path
    beside = {p.stem for kind in ("data", "graphs") for p in preset_files(kind) if not p.is_relative_to(CONF_DIR)}
    assert {"plate_small_pcnoise_0.01", "cavity_cpu_cam1", "plate_equal_radii", "tissue_mgn_near"} <= beside


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


def test_a_preset_may_set_the_sensors_flaws_and_nothing_else_new(tmp_path):
    """The sensor's flaws (off unless set) are the only keys a preset may add; a misspelt one is refused, and
    the loaded sensor section builds the flawed SensorConfig."""
    from ggns.sensors.camera import SensorConfig

    config = load_config("plate_tiny", ["sensor.axial_noise=0.002", "sensor.grazing_angle_deg=70"])
    sensor = SensorConfig.from_dict(config["sensor"])
    assert sensor.axial_noise == 0.002 and sensor.grazing_angle_deg == 70.0 and sensor.has_flaws
    with pytest.raises(UnknownKeyError, match=r"sensor\.axial_nois \(did you mean sensor\.axial_noise"):
        load_config("plate_tiny", ["sensor.axial_nois=0.002"])
    with pytest.raises(UnknownKeyError, match=r"scene\.axial_noise"):
        load_config("plate_tiny", ["scene.axial_noise=0.002"])
    (tmp_path / "dotted.yaml").write_text(f"base: {CONF_DIR / 'data' / 'plate_tiny.yaml'}\nsensor.axial_noise: 0.002\n")
    with pytest.raises(UnknownKeyError, match=r"sensor\.axial_noise"):  # a dotted top-level key is not the flaw
        load_config(tmp_path / "dotted.yaml")


def test_unknown_keys_compares_mappings_only():
    known = {"a": {"b": 1, "c": [1, 2]}, "d": 2}
    assert unknown_keys(known, {"a": {"c": [3]}, "d": {"x": 1}}) == []  # a list or a scalar replaced whole
    assert unknown_keys(known, {"a": {"bb": 1}}) == ["a.bb (did you mean a.b?)"]


def test_experiment_presets_are_found_by_name_after_the_shipped_ones_and_no_name_is_taken_twice():
    """The experiments' sweeps and learning files (experiments/<experiment>/<kind>/) resolve by name in a
    checkout as conf/'s do; conf/ comes first; a name is one preset per kind, so a name never picks one of two."""
    from ggns.config import experiment_dirs, preset_files, resolve_preset

    EXPERIMENTS_DIR = ROOT / "experiments"
    assert experiment_dirs() == [EXPERIMENTS_DIR]  # the checkout's (conftest names it in GGNS_PRESETS)

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


def test_the_package_finds_experiment_presets_only_where_it_is_told(tmp_path, monkeypatch):
    """The installed package never looks outside itself: presets beyond conf/ come from the folders GGNS_PRESETS
    names, else from the working directory's experiments/; elsewhere, with neither, a checkout's are not found."""
    from ggns.config import preset_files, resolve_preset

    (tmp_path / "mine" / "study" / "sweeps").mkdir(parents=True)
    (tmp_path / "mine" / "study" / "sweeps" / "my_sweep.yaml").write_text("output: out\nseeds: [0]\nmodels: {}\n")
    monkeypatch.setenv("GGNS_PRESETS", str(tmp_path / "mine"))
    assert resolve_preset("my_sweep", "sweeps") == tmp_path / "mine" / "study" / "sweeps" / "my_sweep.yaml"
    assert not any(p.stem == "plate_cpu_partition" for p in preset_files("sweeps"))
    monkeypatch.delenv("GGNS_PRESETS")
    monkeypatch.chdir(tmp_path)  # no experiments/ here
    assert [p.parent.parent for p in preset_files("sweeps")] == [CONF_DIR] * len(preset_files("sweeps"))
    with pytest.raises(FileNotFoundError, match="GGNS_PRESETS unset and no ./experiments here"):
        resolve_preset("plate_cpu_partition", "sweeps")
    (tmp_path / "experiments").symlink_to(tmp_path / "mine")
    assert resolve_preset("my_sweep", "sweeps").name == "my_sweep.yaml"


@pytest.mark.parametrize("kind", ["data", "sweeps", "learning", "demo", "bench", None])
def test_every_kind_of_file_extends_its_base_the_same_way(kind, tmp_path):
    """`base:` (ggns.config.base_chain): a file beside this one, or a shipped file of the same kind by name
    (None: a Lightning config); a chain of bases outermost first; a missing base, a cycle and the former
    `extends:` are errors naming the file."""
    from ggns.config import base_chain, config_file, preset_files

    shipped = config_file("trainer") if kind is None else preset_files(kind)[0]
    (tmp_path / "a.yaml").write_text(f"base: {'trainer' if kind is None else shipped.stem}\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\n")
    chain = base_chain(tmp_path / "b.yaml", kind)
    assert chain[-3:] == [shipped, tmp_path / "a.yaml", tmp_path / "b.yaml"], chain
    (tmp_path / "lost.yaml").write_text("base: nowhere.yaml\n")
    with pytest.raises(ValueError, match=r"lost\.yaml: its base 'nowhere\.yaml' is neither a file beside it nor a"):
        base_chain(tmp_path / "lost.yaml", kind)
    (tmp_path / "c.yaml").write_text("base: d.yaml\n")
    (tmp_path / "d.yaml").write_text("base: c.yaml\n")
    with pytest.raises(ValueError, match=r"d\.yaml: its base 'c\.yaml' makes a cycle of bases \(.*c\.yaml -> .*d\.yaml -> .*c\.yaml\)"):
        base_chain(tmp_path / "c.yaml", kind)
    (tmp_path / "old.yaml").write_text("extends: a.yaml\n")
    with pytest.raises(ValueError, match=r"old\.yaml: `extends:` is now `base:`"):
        base_chain(tmp_path / "old.yaml", kind)


def test_a_layered_file_merges_mappings_and_replaces_the_named_keys_whole(tmp_path):
    from ggns.config import load_layered

    (tmp_path / "a.yaml").write_text("x: {p: 1, q: 2}\nv: {one: {}, two: {}}\nn: 1\n")
    (tmp_path / "b.yaml").write_text("base: a.yaml\nx: {q: 3}\nv: {three: {}}\n")
    assert load_layered(tmp_path / "b.yaml", "learning") == {"x": {"p": 1, "q": 3}, "v": {"one": {}, "two": {}, "three": {}},
                                                            "n": 1}
    assert load_layered(tmp_path / "b.yaml", "learning", replace=("v",))["v"] == {"three": {}}
    # a data preset (check=True) over a shipped one by name: only keys the base has
    (tmp_path / "tiny.yaml").write_text("base: plate_tiny\nscene: {num_steps: 6}\n")
    assert load_config(tmp_path / "tiny.yaml")["scene"]["num_steps"] == 6
    assert load_config(tmp_path / "tiny.yaml")["scene"]["grid_nodes"] == load_config("plate_tiny")["scene"]["grid_nodes"]


def test_settings_read_the_same_from_a_mapping_a_file_and_arguments(tmp_path):
    """`command_line` flattens a mapping of Lightning settings into `--dotted.key value` arguments (lists as
    JSON, None as null, booleans lowercase, an append list one argument per item); `settings` reads them back
    from files and arguments alike, a later one winning; `args_mapping` turns the former lists into mappings."""
    from ggns.config import args_mapping, command_line, merge_overrides, settings

    mapping = {"trainer": {"max_time": "00:00:40:00", "check_val_every_n_epoch": None, "enable_progress_bar": False,
                           "callbacks+": ["ggns.callbacks.TrainingClock"]},
               "model": {"class_path": "ggns.models.simulators.GGNSID", "init_args": {"lr_schedule": {"lr": 1e-3}}},
               "evaluation.schedules": ["every:1", "never"], "seed_everything": 1}
    args = command_line(mapping)
    assert args == ["--trainer.max_time", "00:00:40:00", "--trainer.check_val_every_n_epoch", "null",
                    "--trainer.enable_progress_bar", "false", "--trainer.callbacks+", "ggns.callbacks.TrainingClock",
                    "--model.class_path", "ggns.models.simulators.GGNSID", "--model.init_args.lr_schedule.lr", "0.001",
                    "--evaluation.schedules", '["every:1", "never"]', "--seed_everything", "1"]
    (tmp_path / "p.yaml").write_text("trainer: {max_time: '00:00:10:00', limit_val_batches: 8}\n"
                                     "model: {init_args: {lr_schedule: {lr: 1.0e-3}}}\n")
    (tmp_path / "q.yaml").write_text("trainer: {limit_val_batches: 4}\n")
    found = settings(args, [tmp_path / "p.yaml", tmp_path / "q.yaml"])
    assert found["trainer.max_time"] == "00:00:40:00" and found["trainer.limit_val_batches"] == 4  # later wins
    assert found["model.init_args.lr_schedule.lr"] == 0.001 == settings(["--model.init_args.lr_schedule.lr", "1e-3"])[
        "model.init_args.lr_schedule.lr"]
    assert found["trainer.callbacks+"] == ["ggns.callbacks.TrainingClock"]
    assert found["evaluation.schedules"] == ["every:1", "never"] and found["trainer.check_val_every_n_epoch"] is None
    assert args_mapping(["--trainer.max_time", "00:00:40:00", "--data.batch_size", "8", "--data.batch_size=4",
                         "--trainer.callbacks+=a.B"]) == {"trainer": {"max_time": "00:00:40:00", "callbacks+": ["a.B"]},
                                                          "data": {"batch_size": 4}}
    assert merge_overrides({"model": {"init_args": {"latent": 64, "blocks": 3}}, "trainer": {"callbacks+": ["a.B"]}},
                           {"model.init_args.blocks": 5, "trainer": {"callbacks+": ["c.D"]}}) == {
        "model": {"init_args": {"latent": 64, "blocks": 5}}, "trainer": {"callbacks+": ["a.B", "c.D"]}}
