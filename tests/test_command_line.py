"""Parsers built from function signatures (`ggns.cli.parser`) and the commands built with it
(`ggns.cli.commands`, `ggns.cli.bench`, `python -m ggns generate|geometry|bench ...|sweep|demo`)."""
from __future__ import annotations

import re
import shlex
from collections.abc import Sequence
from pathlib import Path
from typing import Literal

import pytest

from ggns.__main__ import main
from ggns.cli.parser import build_parser, call
from ggns.cli.commands import COMMANDS


def sample(*overrides: str, name: str = "plate", count: int | None = None, rate: float = 0.5,
           split: Sequence[Literal["train", "val"]] | None = None, coarsen: Sequence[int] = (1, 2),
           checkpoint: dict[str, str] | None = None, overwrite: bool = False, progress: bool = True,
           device: Literal["cpu", "cuda"] = "cpu"):
    """A sample command.

    Longer text.

    Args:
        overrides: key=value words
        name: a name
        count: how many
        rate: a rate
        split: splits
        coarsen: factors
        checkpoint: checkpoints name=path
        overwrite: replace files
        progress: show progress
        device: where
    """
    return dict(overrides=overrides, name=name, count=count, rate=rate, split=split, coarsen=coarsen,
                checkpoint=checkpoint, overwrite=overwrite, progress=progress, device=device)


def run(argv, commands=None):
    parser = build_parser(commands or {"sample": sample, "group": {"inner": sample}}, prog="t")
    return call(parser.parse_args(argv))


def test_defaults_are_the_functions_defaults():
    assert run(["sample"]) == sample()


def test_options_map_to_parameters():
    got = run(["sample", "--name", "x", "a=1", "b=2", "--count", "3", "--rate", "0.25", "--split", "train",
               "--split", "val", "--coarsen", "1,5", "--coarsen", "7", "--checkpoint", "ggns=/a/b.ckpt",
               "--checkpoint", "mgn=c=d", "--overwrite", "--no-progress", "--device", "cuda"])
    assert got == dict(overrides=("a=1", "b=2"), name="x", count=3, rate=0.25, split=["train", "val"],
                       coarsen=[1, 5, 7], checkpoint={"ggns": "/a/b.ckpt", "mgn": "c=d"}, overwrite=True,
                       progress=False, device="cuda")


def test_nested_commands():
    assert run(["group", "inner", "--count", "4"])["count"] == 4


@pytest.mark.parametrize("argv, message", [
    (["sample", "--split", "test"], "invalid choice: 'test'"),
    (["sample", "--device", "tpu"], "invalid choice: 'tpu'"),
    (["sample", "--coarsen", "1,x"], "invalid int value: 'x'"),
    (["sample", "--count", "many"], "invalid int value: 'many'"),
    (["sample", "--checkpoint", "no-equals"], "expected NAME=VALUE"),
    (["sample", "--nmae", "x"], "unrecognized arguments: --nmae"),
    (["group"], "required"),
])
def test_bad_command_lines_name_the_problem(argv, message, capsys):
    with pytest.raises(SystemExit) as exit:
        run(argv)
    assert exit.value.code == 2
    assert message in capsys.readouterr().err


def test_help_shows_the_docstring(capsys):
    with pytest.raises(SystemExit):
        run(["sample", "--help"])
    out = capsys.readouterr().out
    assert "A sample command." in out and "Longer text." in out
    assert "--count COUNT" in out and "how many" in out and "(default: 1,2)" in out and "--no-progress" in out


def undocumented(a: int = 1, b: int = 2):
    """Has a docstring.

    Args:
        a: documented
    """


def untyped(a=1):
    """Untyped.

    Args:
        a: documented
    """


def required_flag(a: bool):
    """Required.

    Args:
        a: documented
    """


def with_required(path: str, n: int = 1):
    """Has a required option.

    Args:
        path: where
        n: how many
    """
    return path, n


@pytest.mark.parametrize("function, message", [
    (undocumented, "undocumented(b): parameter without a description"),
    (untyped, "untyped(a): parameter without a type annotation"),
    (required_flag, "required_flag(a): only int, float, str and Literal options can be required"),
])
def test_a_command_cannot_grow_an_undocumented_or_untyped_option(function, message):
    with pytest.raises(TypeError, match=message.replace("(", r"\(").replace(")", r"\)")):
        build_parser({"x": function}, prog="t")


def test_every_ggns_command_builds_and_documents_its_options(capsys):
    parser = build_parser(COMMANDS, prog="ggns")  # raises on an undocumented or unsupported parameter
    for argv in (["generate"], ["geometry"], ["bench", "sim"], ["bench", "solvers"], ["bench", "models"], ["bench", "tradeoff"],
                 ["bench", "learning"], ["export"], ["sweep"], ["demo"], ["import-reference"],
                 ["rollout"], ["pretrained", "list"], ["pretrained", "train"], ["pretrained", "package"]):
        with pytest.raises(SystemExit):
            parser.parse_args([*argv, "--help"])
        assert "options:" in capsys.readouterr().out


def test_generate_count_without_split_is_refused(capsys):
    with pytest.raises(SystemExit) as exit:
        main(["generate", "--config", "plate_tiny", "--count", "3"])
    assert exit.value.code == 2
    assert "--count needs --split" in capsys.readouterr().err


ROOT = Path(__file__).resolve().parents[1]
DOCUMENTED = re.compile(r"python -m ggns ((?:generate|import-reference|geometry|bench|sweep|demo|rollout|pretrained)\b"
                        r"(?:[^`\n#|;&)\"']|(?<=\s)\"[^\"`\n,]*\"(?=\s|$))*)")  # a double-quoted argument after a space is one word


def documented_command_lines() -> list[tuple[str, str]]:
    """(file, command line) of every non-Lightning `python -m ggns ...` in the README, docs/, conf/
    and the notebooks: fenced blocks line by line (with `\\` continuations), inline code spans
    joined over their line breaks."""
    found = []
    files = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "conf").rglob("*.yaml")),
             *sorted((ROOT / "notebooks").glob("*.ipynb"))]
    for path in files:
        text = path.read_text().replace("\\\n", " ")
        if path.suffix == ".ipynb":
            text = text.replace("\\n", "\n").replace('\\"', '"')
        parts = re.split(r"^```.*$", text, flags=re.M)
        for index, part in enumerate(parts):
            if index % 2 == 0:  # prose: inline code may wrap
                part = re.sub(r"`[^`]+`", lambda m: m.group(0).replace("\n", " "), part)
            for match in DOCUMENTED.finditer(part):
                found.append((path.relative_to(ROOT).as_posix(), " ".join(match.group(1).split())))
    return found


def test_every_documented_command_line_parses(capsys):
    lines = documented_command_lines()
    assert len(lines) > 40  # the README and docs show dozens
    parser = build_parser(COMMANDS, prog="ggns")
    failed = []
    for where, line in lines:
        words = [re.sub(r"<[^>]*>", "X", w) for w in shlex.split(line)]  # <placeholders>
        try:
            parser.parse_args(words)
        except SystemExit:
            failed.append(f"{where}: {line}: {capsys.readouterr().err.strip().splitlines()[-1]}")
    assert failed == []


def test_a_parameter_without_default_is_a_required_option(capsys):
    assert run(["w", "--path", "p", "--n", "2"], {"w": with_required}) == ("p", 2)
    with pytest.raises(SystemExit):
        run(["w"], {"w": with_required})
    assert "the following arguments are required: --path" in capsys.readouterr().err
