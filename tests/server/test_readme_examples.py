"""server/README.md's copy-paste examples, run against a real `neumip serve` of the shipped `rock`, answer
what the README shows; and the docs page a newcomer opens works offline.

Each example is a fenced block after ``<!-- example: NAME -->``, its output the block after
``<!-- expected: NAME -->``; the test runs the example with the server's URL in place of
``http://127.0.0.1:8000`` and compares every number of the output with the README's to the export's
parity tolerance, so a changed model, format or client makes it fail.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "server" / "README.md"
README_URL = "http://127.0.0.1:8000"
RTOL, ATOL = 1e-4, 1e-5
"""Tolerance of a number against the README's (the export's parity tolerance, |d| <= 1e-5 + 1e-4 |x|)."""
BLOCK = r"<!-- {kind}: (?P<name>[\w-]+) -->\s*```(?P<lang>\w+)\n(?P<code>.*?)```"
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
RUNNERS = {"bash": lambda code: ["bash", "-c", code], "python": lambda code: [sys.executable, "-c", code]}


def blocks(kind: str) -> dict[str, tuple[str, str]]:
    """README blocks marked ``<!-- kind: NAME -->``: NAME -> (fence language, text)."""
    found = re.finditer(BLOCK.format(kind=kind), README.read_text(), flags=re.DOTALL)
    return {m["name"]: (m["lang"], m["code"]) for m in found}


EXAMPLES = blocks("example")


def numbers(text: str) -> np.ndarray:
    return np.array([float(x) for x in NUMBER.findall(text)])


def test_readme_has_the_examples_and_their_outputs():
    assert set(EXAMPLES) == {"curl", "curl-v2", "python-msgpack", "python-client"}
    assert set(blocks("expected")) == set(EXAMPLES)
    for lang, code in EXAMPLES.values():
        assert lang in RUNNERS and README_URL in code


@pytest.fixture(scope="module")
def rock_server(tmp_path_factory):
    """`neumip serve` of the shipped rock alone (loads in a second, not the whole models/ folder)."""
    from neumip.server.process import ServerProcess

    folder = tmp_path_factory.mktemp("rock")
    shutil.copy(ROOT / "models" / "rock.onnx", folder / "rock.onnx")
    server = ServerProcess.start(folder, folder / "server.log", timeout_s=60, warmup_rows=16)
    yield server
    assert server.stop(30) == 0, server.log_tail()


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_readme_example_answers_what_the_readme_shows(rock_server, name):
    lang, code = EXAMPLES[name]
    if lang == "bash" and shutil.which("curl") is None:
        pytest.skip("curl is not installed")
    code = code.replace(README_URL, rock_server.url)
    run = subprocess.run(RUNNERS[lang](code), capture_output=True, text=True, timeout=60, cwd=ROOT, check=False)
    assert run.returncode == 0, run.stderr
    expected = numbers(blocks("expected")[name][1])
    got = numbers(run.stdout)
    assert got.shape == expected.shape, f"output:\n{run.stdout}\nREADME:\n{blocks('expected')[name][1]}"
    np.testing.assert_allclose(got, expected, rtol=RTOL, atol=ATOL, err_msg=run.stdout)


def test_docs_page_loads_only_local_files(client):
    """``/docs`` (Swagger UI) and ``/redoc`` name no CDN: every script, style and icon they load is
    served by the app itself, so the page works without internet."""
    for page in ("/docs", "/redoc"):
        html = client.get(page)
        assert html.status_code == 200
        urls = re.findall(r"""(?:src|href|spec-url)\s*=\s*["']([^"']+)["']|url:\s*["']([^"']+)["']""", html.text)
        urls = [a or b for a, b in urls]
        assert urls and "/openapi.json" in urls, html.text
        assert not re.search(r"https?://|//cdn", html.text, flags=re.IGNORECASE), html.text
        for url in urls:
            assert url.startswith("/") and not url.startswith("//"), url
            got = client.get(url)
            assert got.status_code == 200 and got.content, url
