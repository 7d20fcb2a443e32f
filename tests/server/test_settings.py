"""Settings come from NEUMIP_* environment variables and are checked; `neumip serve` reports bad ones."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import ValidationError

from neumip.client.cli import build_parser, main
from neumip.server.settings import Settings


def test_environment_variables_with_prefix(monkeypatch):
    monkeypatch.setenv("NEUMIP_MODEL_DIR", "/srv/models")
    monkeypatch.setenv("NEUMIP_MAX_WAIT_MS", "0.5")
    monkeypatch.setenv("NEUMIP_ORT_WORKERS", "3")
    settings = Settings()
    assert settings.model_dir == Path("/srv/models")
    assert settings.max_wait_ms == 0.5 and settings.workers() == 3


def test_defaults():
    settings = Settings()
    assert settings.model_dir == Path("models") and settings.host == "127.0.0.1" and settings.port == 8000
    assert settings.workers() >= 1


@pytest.mark.parametrize(
    "bad",
    [{"chunk_rows": 0}, {"max_rows": 10, "max_queue_rows": 5}, {"max_wait_ms": -1}, {"port": 70000},
     {"max_body_bytes": 1 << 30}, {"max_json_body_bytes": 64 << 20}, {"body_timeout_s": 0}],
)
def test_inconsistent_settings_are_rejected(bad):
    with pytest.raises(ValidationError):
        Settings(**bad)


def test_serve_command_options_and_errors(tmp_path, capsys, monkeypatch):
    args = build_parser().parse_args(["serve", "--host", "0.0.0.0", "--port", "9000", "--model-dir", "m"])
    assert (args.host, args.port, args.model_dir) == ("0.0.0.0", 9000, "m")
    assert main(["serve", "--model-dir", str(tmp_path / "missing")]) == 2
    assert "does not exist" in capsys.readouterr().err
    monkeypatch.setenv("NEUMIP_CHUNK_ROWS", "0")
    assert main(["serve", "--model-dir", str(tmp_path)]) == 2
    assert "chunk_rows" in capsys.readouterr().err


def test_list_settings_documents_every_variable(capsys):
    assert main(["serve", "--list-settings"]) == 0
    out = capsys.readouterr().out
    for name in Settings.model_fields:
        assert f"NEUMIP_{name.upper()}" in out
    assert all(len(line.split(None, 2)) == 3 for line in out.strip().splitlines()), "a setting lacks its description"
