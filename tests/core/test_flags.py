"""Flags generated from config dataclasses: every field a flag, its help the field's docstring."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from neumip.core import flags
from neumip.core.config import DERIVED_FIELDS, MaterialConfig


@dataclasses.dataclass(frozen=True)
class Toy:
    """A config of each kind of field."""

    size: int = 4
    """Texels per side. More words."""
    scale: float = 0.5
    """How much (i.e. a factor). Then the rest."""
    mode: str = "a"
    """Which mode."""
    fancy: bool = False
    """Something extra."""
    plain: bool = True
    """Something usual."""


def parse(argv: list[str], **kw) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    flags.add_flags(parser, Toy, choices={"mode": ("a", "b")}, **kw)
    return parser.parse_args(argv)


def test_field_docs_are_the_strings_under_the_fields():
    docs = flags.field_docs(Toy)
    assert docs["size"] == "Texels per side. More words."
    assert flags.first_sentence(docs["scale"]) == "How much (i.e. a factor)."
    assert set(docs) == {"size", "scale", "mode", "fancy", "plain"}


def test_every_field_is_a_flag_of_its_kind():
    args = parse(["--size", "8", "--scale", "2", "--mode", "b", "--fancy", "--no-plain"])
    assert flags.values(args, Toy) == {"size": 8, "scale": 2.0, "mode": "b", "fancy": True, "plain": False}
    assert Toy(**flags.values(args, Toy)) == Toy(8, 2.0, "b", True, False)


def test_flags_not_given_leave_the_defaults():
    assert Toy(**flags.values(parse([]), Toy)) == Toy()
    assert flags.values(parse([], overrides=True), Toy) == {}  # overrides: nothing given, nothing set


def test_an_override_turns_a_bool_either_way():
    """Over a recipe, a bool may be set either way: a recipe may have turned on what is off by default."""
    args = parse(["--no-fancy", "--plain"], overrides=True)
    assert flags.values(args, Toy) == {"fancy": False, "plain": True}
    assert flags.values(parse(["--fancy", "--no-plain"], overrides=True), Toy) == {"fancy": True, "plain": False}


def test_choices_skip_and_rename():
    with pytest.raises(SystemExit):
        parse(["--mode", "c"])
    args = parse(["--toy-size", "2"], skip=("scale",), rename={"size": "toy_size"})
    assert flags.values(args, Toy, skip=("scale",), rename={"size": "toy_size"})["size"] == 2
    with pytest.raises(SystemExit):
        parse(["--scale", "1"], skip=("scale",))


def test_a_new_material_field_is_a_flag_of_train_fit_and_train_many():
    """A MaterialConfig field (not a derived one) needs nothing but its line and docstring to be a flag."""
    from neumip.client.cli import build_parser

    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for command in ("train", "fit", "train-many"):
        dests = {action.dest for action in sub.choices[command]._actions}
        want = {f.name for f in dataclasses.fields(MaterialConfig)} - set(DERIVED_FIELDS)
        if command == "train-many":
            want.discard("offset")  # its --no-offset NAME names the materials without
        assert want <= dests, f"{command} lacks {sorted(want - dests)}"
