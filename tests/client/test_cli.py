"""The `neumip` entry point: version, and options accepted before or after the subcommand."""

from __future__ import annotations

import pytest

from neumip.client import cli


def test_version_prints_the_installed_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"neumip {cli.version()}"
    assert cli.version()[0].isdigit()


@pytest.mark.parametrize("argv", [["-v", "query", "m.onnx", *"0 0 0 0 0 0 0".split()],
                                  ["query", "m.onnx", *"0 0 0 0 0 0 0".split(), "-v"],
                                  ["query", "-v", "m.onnx", *"0 0 0 0 0 0 0".split()]])
def test_verbose_before_or_after_the_subcommand(argv):
    assert cli.build_parser().parse_args(argv).verbose is True


def test_verbose_defaults_to_off():
    assert cli.build_parser().parse_args(["query", "m.onnx", *"0 0 0 0 0 0 0".split()]).verbose is False
