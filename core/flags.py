"""Command-line flags generated from a config dataclass: one flag per field, its help the field's docstring.

nerfstudio generates its flags from its configs (with tyro); neumip's commands are argparse subcommands, and
some of a config's fields are not typed by the user but derived (a pyramid's resolution from the material's
maps), so this is the small part of that idea they need:

- `field_docs(cls)`: each field's docstring (the string literal under it), read from the class's source;
- `add_flags(parser, cls, ...)`: ``--name`` for each field (underscores as dashes) - a bool that is False by
  default is a switch, one that is True by default is ``--no-name``, and where the flags override a recipe both
  ``--name`` and ``--no-name``; a number or string takes a value, with ``choices`` where given - its help the
  docstring's first sentence;
- `values(args, cls)`: the fields a command line set, to pass to `dataclasses.replace` or the constructor.

A field added to the dataclass with a docstring is a flag of every command that adds the class's flags.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import re
import textwrap
from functools import cache


@cache
def field_docs(cls: type) -> dict[str, str]:
    """Field name -> its docstring (the string literal right under the field in the class body)."""
    docs = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                docs[node.target.id] = inspect.cleandoc(after.value.value)
    return docs


def first_sentence(text: str) -> str:
    """The text up to its first full stop followed by a capital (a sentence's end, not "i.e." or "h . wi"), on
    one line."""
    flat = " ".join(text.split())
    end = re.search(r"\.\s+(?=[A-Z0-9])", flat)
    return flat if end is None else flat[: end.start() + 1]


def flag(name: str, default: object = None) -> str:
    """The flag of field `name`: ``--name``, or ``--no-name`` for a bool that is True by default."""
    dashed = name.replace("_", "-")
    return f"--no-{dashed}" if default is True else f"--{dashed}"


def add_flags(parser: argparse.ArgumentParser | argparse._ArgumentGroup, cls: type, *, skip: tuple[str, ...] = (),
              choices: dict[str, tuple] | None = None, overrides: bool = False,
              metavars: dict[str, str] | None = None, rename: dict[str, str] | None = None,
              show_default: bool = False) -> list[str]:
    """Add a flag for each field of dataclass `cls` but those in `skip`; returns the fields added.

    `rename`: field -> the name its flag and its value in the parsed arguments take instead (where two
    configs of one command have a field of the same name).
    `overrides`: the flags override a preset or a recipe, so each defaults to None (not given), and a bool has both
    ``--name`` and ``--no-name`` (a recipe may turn on what is off by default); `show_default` then says the field's
    own default in the help. Otherwise each defaults to the field's default, and a bool is one switch away from it.
    """
    docs, added = field_docs(cls), []
    for field in dataclasses.fields(cls):
        if field.name in skip:
            continue
        default, name = field.default, (rename or {}).get(field.name, field.name)
        help_text = first_sentence(docs.get(field.name, "")).replace("%", "%%") + f" ({cls.__name__}.{field.name})"  # argparse formats help with %
        options = (choices or {}).get(field.name)
        metavar = (metavars or {}).get(field.name)
        if isinstance(default, bool) and overrides:  # --name / --no-name: either may override a recipe's value
            shown = f" (default: {'on' if default else 'off'})" if show_default else ""
            parser.add_argument(f"--{name.replace('_', '-')}", dest=name, action=argparse.BooleanOptionalAction,
                                default=None, help=help_text + shown)
        elif isinstance(default, bool):  # a switch; None when not given, so the config's default holds
            action = "store_false" if default else "store_true"
            parser.add_argument(flag(name, default), dest=name, action=action, default=None,
                                help=("turns off what is on by default: " if default else "") + help_text)
        else:
            kind = type(default)
            shown = f" (default: {default})" if overrides and show_default else ""
            parser.add_argument(flag(name), dest=name, type=kind, choices=options, metavar=metavar,
                                default=None if overrides else default, help=help_text + shown)
        added.append(field.name)
    return added


def values(args: argparse.Namespace, cls: type, skip: tuple[str, ...] = (),
           rename: dict[str, str] | None = None) -> dict[str, object]:
    """The fields of `cls` that `args` holds a value for (None: not given), but those in `skip`."""
    names = {f.name: (rename or {}).get(f.name, f.name) for f in dataclasses.fields(cls) if f.name not in skip}
    return {field: getattr(args, name) for field, name in names.items() if getattr(args, name, None) is not None}
