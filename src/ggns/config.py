"""Loading YAML presets from conf/: a preset may name a `base` preset (relative path) that it
overrides, and command-line `key=value` dotlist overrides apply last."""
from __future__ import annotations

from pathlib import Path

from omegaconf import OmegaConf

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"


def resolve_preset(name: str | Path, kind: str = "data") -> Path:
    """A path to an existing YAML file, or a preset name looked up in conf/<kind>/<name>.yaml."""
    path = Path(name)
    if path.is_file():
        return path
    candidate = CONF_DIR / kind / f"{name}.yaml"
    if candidate.is_file():
        return candidate
    known = sorted(p.stem for p in (CONF_DIR / kind).glob("*.yaml"))
    raise FileNotFoundError(f"no config file {str(name)!r} and no preset of that name in {CONF_DIR / kind} (known: {known})")


def load_config(name: str | Path, overrides: list[str] = (), kind: str = "data") -> dict:
    """The merged configuration as a plain dict."""
    path = resolve_preset(name, kind)
    cfg = OmegaConf.load(path)
    base = cfg.pop("base", None)
    if base is not None:
        cfg = OmegaConf.merge(OmegaConf.create(load_config(path.parent / base, kind=kind)), cfg)
    if overrides:
        cfg = OmegaConf.merge(cfg, OmegaConf.from_dotlist(list(overrides)))
    return OmegaConf.to_container(cfg, resolve=True)
