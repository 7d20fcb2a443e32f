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


def test_bare_neumip_prints_the_help(capsys):
    assert cli.main([]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: neumip") and "fit" in out and "render" in out and "serve" in out


def test_serve_says_where_it_listens_and_logs_no_colour_codes(model_dir, serve, monkeypatch):
    """The server's log names its address, and where ONNX Runtime cannot write its telemetry cache (a
    container user without a home) it carries no raw ANSI colour codes from ONNX Runtime's warning."""
    monkeypatch.setenv("HOME", "/proc/neumip-no-home")  # cannot be created, not even by root
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.delenv("ORT_DISABLE_TELEMETRY", raising=False)
    server = serve()
    log = server.log.read_text()
    assert f"listening on {server.url}" in log, log
    assert "\x1b[" not in log and "telemetry" not in log, log


def test_verbose_defaults_to_off():
    assert cli.build_parser().parse_args(["query", "m.onnx", *"0 0 0 0 0 0 0".split()]).verbose is False


def test_query_by_file_or_by_name_in_models(model_dir, capsys):
    assert cli.main(["query", str(model_dir / "lambert.onnx"), *"0.3 0.7 0.01 0.2 0.1 -0.3 0.4".split()]) == 0
    by_file = capsys.readouterr().out
    assert [float(x) for x in by_file.split()] == pytest.approx([0.5 / 3.141592653589793] * 3, rel=1e-5)
    values = "0.3 0.7 0.01 0.2 0.1 -0.3 0.4".split()
    assert cli.main(["query", "lambert", *values, "--models", str(model_dir)]) == 0
    assert capsys.readouterr().out == by_file


def test_query_errors_say_what_is_wrong(model_dir, tmp_path, capsys):
    values = "0 0 0 0 0 0 0".split()
    assert cli.main(["query", str(model_dir), *values]) == 2
    assert f"{model_dir} is a directory: give a material's .onnx file, or a material name with --models" in \
        capsys.readouterr().err
    assert cli.main(["query", "velvet", *values, "--models", str(model_dir)]) == 2
    assert "no material 'velvet' in" in (err := capsys.readouterr().err) and "flat16, lambert, rand16" in err
    assert cli.main(["query", str(tmp_path / "gone.onnx"), *values]) == 2
    assert "gone.onnx does not exist" in capsys.readouterr().err


def test_help_documents_the_query_values_and_the_defaults(capsys):
    from neumip.core import contract as C

    with pytest.raises(SystemExit):
        cli.main(["query", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert " ".join(C.QUERY_FIELDS) in text and "towards the light" in text and "(default: models)" in text
    for argv, expected in [(["train", "--help"], "(default: ship)"),
                           (["render", "--help"], "(default: models)")]:
        with pytest.raises(SystemExit):
            cli.main(argv)
        assert expected in " ".join(capsys.readouterr().out.split()), argv
