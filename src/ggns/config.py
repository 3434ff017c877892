"""Loading YAML presets from conf/: a preset may name a `base` preset (relative path) that it
overrides, and command-line `key=value` dotlist overrides apply last.

Neither can add a key: every key a preset sets over its base, and every override, must already be
in the configuration it changes (the root preset defines the keys), or loading fails with
`UnknownKeyError` naming the key and the nearest valid ones. A typo such as `scene.gird_nodes=5`
would otherwise be stored and silently ignored."""
from __future__ import annotations

import difflib
from pathlib import Path

from omegaconf import OmegaConf

CONF_DIR = Path(__file__).resolve().parent / "conf"  # shipped inside the package; conf/ at the checkout's top links here


def config_file(spec: str | Path) -> Path:
    """A Lightning config named by a path that exists, by its path in a checkout (`conf/plate/ggns.yaml`,
    which works from any folder: `conf/` is the package's own), or by its name under the package's conf
    (`plate/ggns`, `plate/ggns.yaml`). Anything else is returned unchanged, for the caller to refuse."""
    path = Path(spec)
    if path.is_file():
        return path
    parts = path.parts[1:] if path.parts[:1] == ("conf",) else path.parts
    for candidate in (CONF_DIR.joinpath(*parts), CONF_DIR.joinpath(*parts).with_suffix(".yaml")):
        if parts and candidate.is_file():
            return candidate
    return path


# The presets of the project's own experiments (sweeps and learning files that answered one question, each
# beside its page in docs/experiments/): experiments/<experiment>/<kind>/<name>.yaml at a checkout's top, not
# shipped in the package. A checkout finds them by name as it finds conf/'s; an installed package does not.
EXPERIMENTS_DIR = CONF_DIR.parents[2] / "experiments"


def preset_files(kind: str) -> list[Path]:
    """Every preset of a kind by name: conf/<kind>/*.yaml, then a checkout's experiments/*/<kind>/*.yaml."""
    return sorted((CONF_DIR / kind).glob("*.yaml")) + sorted(EXPERIMENTS_DIR.glob(f"*/{kind}/*.yaml"))


def resolve_preset(name: str | Path, kind: str = "data") -> Path:
    """A path to an existing YAML file, or a preset name: conf/<kind>/<name>.yaml, else the experiment preset
    experiments/*/<kind>/<name>.yaml of a checkout (`preset_files`)."""
    path = Path(name)
    if path.is_file():
        return path
    found = [p for p in preset_files(kind) if p.stem == str(name)]
    if found:
        return found[0]
    known = sorted({p.stem for p in preset_files(kind)})
    raise FileNotFoundError(f"no config file {str(name)!r} and no preset of that name in {CONF_DIR / kind} "
                            f"or {EXPERIMENTS_DIR}/*/{kind} (known: {known})")


class UnknownKeyError(ValueError):
    """A preset or an override sets a key that the configuration it changes does not have."""


def unknown_keys(known: dict, update: dict, prefix: str = "") -> list[str]:
    """The dotted keys of `update` that `known` lacks, each with the nearest known keys at its level
    ("scene.gird_nodes (did you mean scene.grid_nodes?)"). Mappings are compared key by key;
    anything else (numbers, strings, lists) replaces the known value whole."""
    problems = []
    for key, value in update.items():
        path = f"{prefix}{key}"
        if key not in known:
            near = difflib.get_close_matches(str(key), [str(k) for k in known], n=3, cutoff=0.5)
            hint = f" (did you mean {' or '.join(prefix + k for k in near)}?)" if near else \
                f" (known at this level: {sorted(map(str, known))})"
            problems.append(path + hint)
        elif isinstance(value, dict) and isinstance(known[key], dict):
            problems += unknown_keys(known[key], value, path + ".")
    return problems


def checked_merge(known: dict, update: dict, source: str) -> dict:
    """`update` merged over `known` (plain dicts), refusing keys `known` does not have."""
    problems = unknown_keys(known, update)
    if problems:
        raise UnknownKeyError(f"unknown key(s) in {source}: {'; '.join(problems)}")
    return OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(known), OmegaConf.create(update)), resolve=True)


def load_config(name: str | Path, overrides: list[str] = (), kind: str = "data") -> dict:
    """The merged configuration as a plain dict (keys checked: module docstring)."""
    path = resolve_preset(name, kind)
    cfg = OmegaConf.to_container(OmegaConf.load(path), resolve=False)
    base = cfg.pop("base", None)
    if base is not None:
        cfg = checked_merge(load_config(path.parent / base, kind=kind), cfg, f"{path} (over its base {base})")
    if overrides:
        cfg = checked_merge(cfg, OmegaConf.to_container(OmegaConf.from_dotlist(list(overrides))),
                            f"the overrides {list(overrides)}")
    return OmegaConf.to_container(OmegaConf.create(cfg), resolve=True)


def dataclass_of(cls, value, what: str):
    """A dataclass `cls` (a model's part, `TrainingNoise`, `LRSchedule`) from itself, a mapping of its fields
    (a config, a checkpoint's hyperparameters) or None (its defaults); an unknown field raises ValueError
    naming `what` and the known fields, another type TypeError."""
    import dataclasses
    from collections.abc import Mapping

    if value is None:
        return cls()
    if isinstance(value, cls):
        return value
    if not isinstance(value, Mapping):
        raise TypeError(f"{what} must be a {cls.__name__} or a mapping of its fields, got {type(value).__name__}")
    known = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(value) - set(known))
    if unknown:
        raise ValueError(f"{what}: unknown fields {unknown} (known: {known})")
    return cls(**value)

