"""argparse parsers built from function signatures and their docstrings.

A command is a plain function: its Google-style docstring gives the command's help (first
paragraph) and each parameter's help (`Args:`), its annotations give the option types. The
mapping, chosen so the options read like a Unix command line:

- a parameter `train_batches: int = 10` becomes the option `--train-batches N` (dashes for
  underscores); `X | None = None` is an optional `X`;
- `bool = False` is a flag (`--overwrite`); `bool = True` gives `--name / --no-name`;
- `Literal["a", "b"]` restricts the values (`choices`);
- a sequence (`tuple[str, ...]`, `list[int]`, ...) takes comma-separated values and may be
  repeated (`--split train --split val` == `--split train,val`);
- `dict[str, str]` is a repeatable `--name KEY=VALUE`;
- `*args: str` collects the positional words (`key=value` overrides);
- a parameter without a default is a required option (int, float, str or Literal).

A nested mapping of commands gives sub-commands (`bench sim`, `bench models`). Parameters without
a docstring entry are an error when the parser is built (so a command cannot grow an undocumented
option). jsonargparse (the Lightning CLI's parser) was not used for these commands: it has no
variadic positionals, no bare boolean flags and no dashed option names, so every documented command
line would have changed.
"""
from __future__ import annotations

import argparse
import inspect
import types
import typing
from collections.abc import Callable, Mapping, Sequence

import docstring_parser

Command = Callable[..., object]
Commands = Mapping[str, "Command | Commands"]


def option_name(parameter: str) -> str:
    return "--" + parameter.replace("_", "-")


def _strip_optional(annotation):
    """`X | None` / `Optional[X]` -> X (other unions are not supported)."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        members = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(members) != 1:
            raise TypeError(f"only `X | None` unions are supported as options, got {annotation}")
        return members[0]
    return annotation


def _converter(annotation, where: str):
    """(type callable, choices) for one value of `annotation`."""
    if typing.get_origin(annotation) is typing.Literal:
        values = typing.get_args(annotation)
        kind = type(values[0])
        return kind, list(values)
    if annotation in (int, float, str):
        return annotation, None
    raise TypeError(f"{where}: unsupported option type {annotation!r} (int, float, str, bool, Literal, sequences "
                    "of those, dict[str, str])")


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key or not value:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE, got {text!r}")
    return key, value


class _AppendSplit(argparse.Action):
    """Repeatable option whose values may also be comma-separated; each value converted by `convert`."""

    def __init__(self, *args, convert=str, choices_=None, **kwargs):
        super().__init__(*args, **kwargs)
        self.convert, self.choices_ = convert, choices_

    def __call__(self, parser, namespace, text, option_string=None):
        items = list(getattr(namespace, self.dest, None) or [])
        for word in (w.strip() for w in text.split(",")):
            if not word:
                continue
            try:
                value = self.convert(word)
            except ValueError:
                parser.error(f"argument {option_string}: invalid {self.convert.__name__} value: {word!r}")
            if self.choices_ is not None and value not in self.choices_:
                parser.error(f"argument {option_string}: invalid choice: {word!r} (choose from "
                             f"{', '.join(map(str, self.choices_))})")
            items.append(value)
        setattr(namespace, self.dest, items)


class _AppendKeyValue(argparse.Action):
    def __call__(self, parser, namespace, text, option_string=None):
        items = dict(getattr(namespace, self.dest, None) or {})
        try:
            key, value = _key_value(text)
        except argparse.ArgumentTypeError as error:
            parser.error(f"argument {option_string}: {error}")
        items[key] = value
        setattr(namespace, self.dest, items)


def add_command(parser: argparse.ArgumentParser, function: Command) -> argparse.ArgumentParser:
    """Add one option per parameter of `function` to `parser` (module docstring) and make it run `function`."""
    docs = docstring_parser.parse(inspect.getdoc(function) or "")
    helps = {p.arg_name.lstrip("*"): (p.description or "").replace("\n", " ") for p in docs.params}
    hints = typing.get_type_hints(function)
    name = function.__name__
    for parameter in inspect.signature(function).parameters.values():
        where = f"{name}({parameter.name})"
        if parameter.name not in helps or not helps[parameter.name]:
            raise TypeError(f"{where}: parameter without a description in the docstring's Args section")
        if parameter.name not in hints:
            raise TypeError(f"{where}: parameter without a type annotation")
        annotation, help_text = hints[parameter.name], helps[parameter.name]
        if parameter.kind is inspect.Parameter.VAR_POSITIONAL:
            parser.add_argument("_positional", nargs="*", metavar=parameter.name.upper(), help=help_text)
            continue
        if parameter.kind is inspect.Parameter.VAR_KEYWORD:
            raise TypeError(f"{where}: **kwargs cannot become options")
        required = parameter.default is inspect.Parameter.empty
        default = None if required else parameter.default
        flag = option_name(parameter.name)
        kind = _strip_optional(annotation)
        origin = typing.get_origin(kind)
        shown = f" (default: {default})" if default not in (None, False, "", ()) else ""
        if required and (kind is bool or typing.get_origin(kind) is not None and typing.get_origin(kind) is not typing.Literal):
            raise TypeError(f"{where}: only int, float, str and Literal options can be required (give it a default)")
        if kind is bool:
            if default:
                parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=True, help=help_text)
            else:
                parser.add_argument(flag, action="store_true", help=help_text)
        elif origin in (dict, Mapping):
            parser.add_argument(flag, action=_AppendKeyValue, default=None, metavar="NAME=VALUE",
                                help=help_text + " (repeatable)")
        elif origin in (list, tuple, Sequence):
            item = typing.get_args(kind)[0]
            convert, choices = _converter(item, where)
            shown = f" (default: {','.join(map(str, default))})" if default else ""
            parser.add_argument(flag, action=_AppendSplit, convert=convert, choices_=choices, default=None,
                                help=help_text + " (comma-separated or repeated)" + shown)
        elif required:
            convert, choices = _converter(kind, where)
            parser.add_argument(flag, type=convert, choices=choices, required=True, help=help_text + " (required)")
        else:
            convert, choices = _converter(kind, where)
            parser.add_argument(flag, type=convert, choices=choices, default=default, help=help_text + shown)
    parser.set_defaults(_function=function)
    return parser


def build_parser(commands: Commands, prog: str, description: str = "") -> argparse.ArgumentParser:
    """A parser with one sub-command per entry of `commands` (a nested mapping gives sub-sub-commands)."""
    parser = argparse.ArgumentParser(prog=prog, description=description,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_commands(parser, commands, prog)
    return parser


def _add_commands(parser: argparse.ArgumentParser, commands: Commands, path: str) -> None:
    sub = parser.add_subparsers(dest=f"_command_{path}", required=True, metavar="{" + ",".join(commands) + "}")
    for name, entry in commands.items():
        if isinstance(entry, Mapping):
            first = f"{name} sub-commands: " + ", ".join(entry)
            child = sub.add_parser(name, help=first, description=first)
            _add_commands(child, entry, f"{path} {name}")
        else:
            docs = docstring_parser.parse(inspect.getdoc(entry) or "")
            if not docs.short_description:
                raise TypeError(f"command {path} {name}: the function {entry.__name__} has no docstring")
            description = "\n\n".join(t for t in (docs.short_description, docs.long_description) if t)
            child = sub.add_parser(name, help=docs.short_description.rstrip("."), description=description,
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
            add_command(child, entry)


def call(args: argparse.Namespace):
    """Run the function the parsed command line names, with its arguments (sequence and mapping
    options not given take the function's default)."""
    function = args._function
    positional, keywords = [], {}
    for parameter in inspect.signature(function).parameters.values():
        if parameter.kind is inspect.Parameter.VAR_POSITIONAL:
            positional = list(args._positional)
        else:
            value = getattr(args, parameter.name)
            keywords[parameter.name] = parameter.default if value is None else value
    return function(*positional, **keywords)
