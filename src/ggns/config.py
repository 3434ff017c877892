"""Loading YAML files from conf/ (and a checkout's experiments/), and the Lightning settings they hold.

Inheritance, the same for every kind of file (Lightning configs, data presets, sweep, learning, demo
and bench files): a top-level `base:` names the file this one extends, by a path relative to it or
by the name of a shipped file of the same kind (`trainer` for a Lightning config, `plate` for a data
preset, `plate_cpu` for a sweep); the base applies first and the file's own keys on top, mappings
key by key (`base_chain`, `load_layered`). A base that is not found, or a chain of bases that comes
back to a file, is a ValueError naming the file.

Data presets are checked besides: every key a preset sets over its base, and every command-line
`key=value` override, must already be in the configuration it changes (the root preset defines the
keys), or loading fails with `UnknownKeyError` naming the key and the nearest valid ones. A typo such
as `scene.gird_nodes=5` would otherwise be stored and silently ignored. The one exception: the sensor's
flaws (`OPTIONAL_KEYS`), off unless a preset sets them.

Lightning settings in sweep, learning and demo files are YAML mappings of the Lightning CLI's keys
(`overrides: {trainer: {max_time: "00:00:40:00"}, model: {init_args: {latent: 64}}}`) and config
files stacked after a model's config (`configs: [conf/profiles/cpu.yaml]`); `command_line` writes a
mapping as the `--dotted.key value` arguments of a `python -m ggns fit` command."""
from __future__ import annotations

import copy
import difflib
import os
import json
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import yaml
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


# Presets by name beyond the package's own conf/: folders laid out as experiments/<experiment>/<kind>/<name>.yaml
# (the project's own experiments, each beside its page in docs/experiments/, are such a folder at a checkout's
# top; they are not shipped in the package). The package never looks outside itself for them: the folders are
# the ones GGNS_PRESETS lists (separated by os.pathsep), else the working directory's experiments/.
PRESETS_ENV = "GGNS_PRESETS"


def experiment_dirs() -> list[Path]:
    """The folders searched for presets by name after conf/ (see `PRESETS_ENV`): `GGNS_PRESETS`'s, else
    ./experiments when the working directory has one (a checkout's top)."""
    listed = os.environ.get(PRESETS_ENV)
    if listed is not None:
        return [Path(p).expanduser() for p in listed.split(os.pathsep) if p]
    here = Path.cwd() / "experiments"
    return [here] if here.is_dir() else []


def preset_files(kind: str) -> list[Path]:
    """Every preset of a kind by name: conf/<kind>/*.yaml, then <folder>/*/<kind>/*.yaml of each
    `experiment_dirs` folder."""
    return sorted((CONF_DIR / kind).glob("*.yaml")) + [p for d in experiment_dirs()
                                                        for p in sorted(d.glob(f"*/{kind}/*.yaml"))]


def resolve_preset(name: str | Path, kind: str = "data") -> Path:
    """A path to an existing YAML file, or a preset name: conf/<kind>/<name>.yaml, else an experiment preset
    <folder>/*/<kind>/<name>.yaml of the `experiment_dirs` (`preset_files`)."""
    path = Path(name)
    if path.is_file():
        return path
    found = [p for p in preset_files(kind) if p.stem == str(name)]
    if found:
        return found[0]
    known = sorted({p.stem for p in preset_files(kind)})
    where = " or ".join(f"{d}/*/{kind}" for d in experiment_dirs()) or \
        f"experiment folders ({PRESETS_ENV} unset and no ./experiments here)"
    raise FileNotFoundError(f"no config file {str(name)!r} and no preset of that name in {CONF_DIR / kind} "
                            f"or {where} (known: {known})")


class UnknownKeyError(ValueError):
    """A preset or an override sets a key that the configuration it changes does not have."""


# Keys a data preset may set though the root preset does not: the sensor's flaws, all off unless set
# (`ggns.sensors.camera.SensorConfig`; their preset values: `SENSOR_FLAWS`).
OPTIONAL_KEYS = frozenset(f"sensor.{name}" for name in ("axial_noise", "grazing_angle_deg", "edge_threshold",
                                                        "outlier_fraction", "outlier_range", "extrinsic_error"))


def unknown_keys(known: dict, update: dict, prefix: str = "") -> list[str]:
    """The dotted keys of `update` that `known` lacks, each with the nearest known keys at its level
    ("scene.gird_nodes (did you mean scene.grid_nodes?)"). Mappings are compared key by key;
    anything else (numbers, strings, lists) replaces the known value whole."""
    problems = []
    for key, value in update.items():
        path = f"{prefix}{key}"
        if path in OPTIONAL_KEYS and "." not in str(key):  # `sensor: {axial_noise: ..}`, not a dotted top-level key
            continue
        if key not in known:
            optional = [k[len(prefix):] for k in OPTIONAL_KEYS if k.rsplit(".", 1)[0] + "." == prefix]
            near = difflib.get_close_matches(str(key), [str(k) for k in known] + optional, n=3, cutoff=0.5)
            hint = f" (did you mean {' or '.join(prefix + k for k in near)}?)" if near else \
                f" (known at this level: {sorted(map(str, known)) + sorted(optional)})"
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


# ---- inheritance: `base:` in every kind of file ---------------------------------------------------
def _named_base(path: Path, kind: str | None) -> str | None:
    """The `base:` a file names (None when it names none)."""
    try:
        own = yaml.safe_load(path.read_text())
    except yaml.YAMLError as error:
        if kind is None:
            return None  # a Lightning config: the CLI's parser names the problem
        raise ValueError(f"{path}: not valid YAML ({error})") from error
    if not isinstance(own, dict):
        return None
    if "extends" in own:
        raise ValueError(f"{path}: `extends:` is now `base:` (the file this one extends: a path relative to it, or "
                         f"a shipped file's name)")
    base = own.get("base")
    if base is not None and not isinstance(base, str):
        hint = (" (a learning file's run settings, once `base: {config, args}`, are now `run: {config, configs, "
                "overrides}`)" if isinstance(base, dict) and "config" in base else "")
        raise ValueError(f"{path}: `base:` names the one file this one extends (a path relative to it, or a shipped "
                         f"file's name), got {base!r}{hint}")
    return base


def _find_base(path: Path, base: str, kind: str | None) -> Path | None:
    """`base` as a file beside `path` (or an absolute path), else a shipped file of the kind by name: a
    Lightning config (`config_file`) when `kind` is None, else a preset of that kind (`preset_files`)."""
    beside = path.parent / base
    if beside.is_file():
        return beside
    if kind is None:
        found = config_file(base)
        return found if found.is_file() else None
    return next((p for p in preset_files(kind) if p.stem == base or p.name == base), None)


def _chain(path: Path, kind: str | None) -> list[tuple[Path, str | None]]:
    """(file, the base it names) from the outermost base to `path` (`base_chain`)."""
    chain = [(path, _named_base(path, kind))]
    seen = [path.resolve()]
    what = "shipped config" if kind is None else f"preset of conf/{kind}/ or experiments/*/{kind}/"
    while chain[0][1] is not None:
        current, base = chain[0]
        found = _find_base(current, base, kind)
        if found is None:
            raise ValueError(f"{current}: its base {base!r} is neither a file beside it nor a {what}")
        if found.resolve() in seen:
            raise ValueError(f"{current}: its base {base!r} makes a cycle of bases "
                             f"({' -> '.join(str(p) for p in [*seen, found])})")
        seen.append(found.resolve())
        chain.insert(0, (found, _named_base(found, kind)))
    return chain


def base_chain(path: str | Path, kind: str | None = None) -> list[Path]:
    """The files that make up `path`, outermost base first and `path` last: its top-level `base:` (a path
    relative to it, or a shipped file of the same kind by name: a Lightning config such as `trainer` when
    `kind` is None, else a preset of conf/<kind>/ or a checkout's experiments/*/<kind>/), that file's base,
    and so on. A base that is not found, a cycle, or `extends:` (its former name in learning files) raises
    ValueError naming the file. One mechanism for every kind of file: Lightning configs are stacked as
    `--config` files in this order (`ggns.cli.config_bases`), the others merged by `load_layered`."""
    return [file for file, _ in _chain(Path(path), kind)]


def load_layered(path: str | Path, kind: str, replace: Sequence[str] = (), check: bool = False) -> dict:
    """A file over its bases (`base_chain`) as one plain dict without `base`: each file's keys over the
    ones before it, mappings merged key by key, except the top-level keys in `replace` (a learning file's
    `variants`, a sweep's `models`), which a file that has them replaces whole. `check`: a file may only
    change keys its bases have (`checked_merge`, the data presets' rule)."""
    chain = _chain(Path(path), kind)
    key = (kind, tuple(replace), check, tuple((str(file.resolve()), file.read_text()) for file, _ in chain))
    merged = _LAYERED.get(key)
    if merged is None:
        if len(_LAYERED) >= 256:
            _LAYERED.clear()
        merged = _LAYERED[key] = _merge_chain(chain, replace, check)
    return copy.deepcopy(merged)


_LAYERED: dict[tuple, dict] = {}
"""`load_layered`'s merged files by their kind, rules and the paths and texts of the chain: a file read again
unchanged is not merged again (OmegaConf's merge and interpolation take about 0.1 s a preset)."""


def _merge_chain(chain: list[tuple[Path, str | None]], replace: Sequence[str], check: bool) -> dict:
    merged: dict | None = None
    for file, named in chain:
        own = OmegaConf.to_container(OmegaConf.load(file), resolve=False) or {}
        if not isinstance(own, dict):
            raise ValueError(f"{file}: expected a mapping of keys, got {type(own).__name__}")
        own.pop("base", None)
        if merged is None:
            merged = own
        else:
            whole = {key: own.pop(key) for key in replace if key in own}
            merged = (checked_merge(merged, own, f"{file} (over its base {named})") if check else
                      OmegaConf.to_container(OmegaConf.merge(OmegaConf.create(merged), OmegaConf.create(own))))
            merged.update(whole)
    return OmegaConf.to_container(OmegaConf.create(merged), resolve=True)


# ---- Lightning settings as mappings ---------------------------------------------------------------
# The top-level keys of a Lightning CLI config (`python -m ggns fit --print_config`): what an `overrides`
# mapping may hold.
LIGHTNING_KEYS = ("seed_everything", "trainer", "model", "data", "evaluation")


def nested(mapping: Mapping) -> dict:
    """`mapping` with its dotted keys (`trainer.max_time: ...`) as nested mappings (`trainer: {max_time: ...}`)."""
    out: dict = {}
    for key, value in mapping.items():
        *parents, last = str(key).split(".")
        node = out
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ValueError(f"{key}: {'.'.join(parents)} is both a value and a mapping")
        value = nested(value) if isinstance(value, Mapping) else value
        node[last] = merge_overrides(node[last], value) if isinstance(node.get(last), dict) and isinstance(value, dict) \
            else value
    return out


def merge_overrides(*mappings: Mapping) -> dict:
    """The mappings merged in order, later ones winning key by key (mappings merged recursively, dotted keys
    nested first); a `key+` list (`callbacks+`: Lightning's append) is joined, not replaced."""
    out: dict = {}
    for mapping in mappings:
        for key, value in nested(mapping or {}).items():
            if isinstance(value, dict) and isinstance(out.get(key), dict):
                out[key] = merge_overrides(out[key], value)
            elif key.endswith("+") and isinstance(out.get(key), list):
                out[key] = out[key] + list(value if isinstance(value, (list, tuple)) else [value])
            else:
                out[key] = value
    return out


def command_value(value) -> str:
    """A value as the Lightning CLI reads it on a command line: null, true / false, numbers as Python
    writes them, strings as they are, lists and mappings as JSON."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple, dict)):
        return json.dumps(value)
    return str(value)


def command_line(overrides: Mapping) -> list[str]:
    """The `--dotted.key value` arguments of a mapping of Lightning settings, in its order: nested
    mappings flattened (`{model: {init_args: {latent: 64}}}` -> `--model.init_args.latent 64`), each item
    of a `key+` list appended on its own (`--trainer.callbacks+ ggns.callbacks.TrainingClock`)."""
    args: list[str] = []

    def walk(node: Mapping, prefix: str) -> None:
        for key, value in node.items():
            name = f"{prefix}{key}"
            if isinstance(value, Mapping) and value and not name.endswith("+"):
                walk(value, name + ".")
            elif name.endswith("+") and isinstance(value, (list, tuple)):
                for item in value:
                    args.extend([f"--{name}", command_value(item)])
            elif not (isinstance(value, Mapping) and not value):
                args.extend([f"--{name}", command_value(value)])

    walk(nested(overrides), "")
    return args


_NUMBER = re.compile(r"[-+]?(\d[\d_]*)?\.?\d*([eE][-+]?\d+)?")


def parse_value(text: str):
    """A command-line value as a Python value, for comparing settings: null, true / false, a number, a
    JSON or YAML list or mapping, else the string itself (`00:00:40:00` stays a string)."""
    lowered = text.strip().lower()
    if lowered in ("null", "none", "~"):
        return None
    if lowered in ("true", "false"):
        return lowered == "true"
    if re.fullmatch(r"[-+]?\d+", text.strip()):
        return int(text)
    if _NUMBER.fullmatch(text.strip()) and any(c.isdigit() for c in text):
        return float(text)
    if text.strip().startswith(("[", "{")):
        try:
            return yaml.safe_load(text)
        except yaml.YAMLError:
            return text
    return text


def settings(args: Sequence[str] = (), files: Sequence[str | Path] = ()) -> dict:
    """The Lightning settings that config `files` (in order, each after its bases) and then command-line
    `args` (`--key value` or `--key=value`) make, as {dotted key: value} with values compared as the CLI
    reads them (`parse_value`: `1e-3` == `0.001`); a `key+` (an append) collects its items in a list.
    Files are flattened as `command_line` writes a mapping, so a setting reads the same from a file or from
    arguments."""
    flat: list[str] = []
    for file in files:
        for layer in base_chain(config_file(str(file))):
            own = yaml.safe_load(layer.read_text()) or {}
            flat += command_line({k: v for k, v in own.items() if k != "base"})
    out: dict = {}
    items = [*flat, *map(str, args)]
    i = 0
    while i < len(items):
        arg = items[i]
        if not arg.startswith("--"):
            raise ValueError(f"{arg!r} in {list(args)}: expected --key value")
        if "=" in arg:
            key, value = arg[2:].split("=", 1)
            i += 1
        elif i + 1 < len(items):
            key, value = arg[2:], items[i + 1]
            i += 2
        else:
            raise ValueError(f"{arg} has no value in {list(args)}")
        value = parse_value(value)
        if key.endswith("+"):
            out[key] = [*out.get(key, []), *(value if isinstance(value, list) else [value])]
        else:
            out[key] = value
    return out


def args_mapping(args: Sequence[str]) -> dict:
    """A list of command-line arguments (`["--trainer.max_time", "00:00:40:00"]`, the former form of
    overrides) as the mapping that says the same (`{trainer: {max_time: "00:00:40:00"}}`)."""
    return nested(settings(args))


def old_form_error(source: str, args, example: str = "overrides") -> ValueError:
    """The error for a list of command-line strings where a mapping of Lightning settings now goes."""
    try:
        suggestion = yaml.safe_dump(args_mapping([str(a) for a in args]), default_flow_style=True, width=10 ** 6,
                                    sort_keys=False).strip()
    except ValueError:
        suggestion = "{trainer: {max_time: '00:00:40:00'}, model: {init_args: {latent: 64}}}"
    return ValueError(f"{source}: a list of command-line strings is the former form; Lightning settings are now a "
                      f"mapping of their keys ({example}: {suggestion}), shared ones a config file under `configs:`")


def load_config(name: str | Path, overrides: list[str] = (), kind: str = "data") -> dict:
    """The merged configuration as a plain dict (keys checked: module docstring)."""
    path = resolve_preset(name, kind)
    cfg = load_layered(path, kind, check=True)
    if not overrides:
        return cfg  # resolved by load_layered
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

