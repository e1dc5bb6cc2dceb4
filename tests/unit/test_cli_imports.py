"""``v2i`` parses a command with that command's modules only: ``v2i --help`` imports no
numpy, scipy, Zenoh or pydantic; each command parses as it does in the full parser."""

from __future__ import annotations

import ast
import subprocess
import sys

import pytest

from v2i.cli import SUBCOMMANDS, _named_command, build_parser

HEAVY = ("numpy", "scipy", "zenoh", "pydantic", "yaml", "msgpack", "obu_service.pipeline", "link_emulator.cli")


def _imported_after(argv: list[str]) -> list[str]:
    """The HEAVY modules loaded by ``v2i.cli.main(argv)`` in a fresh interpreter."""
    code = (
        "import sys\nfrom v2i.cli import main\n"
        f"try:\n    main({argv!r})\nexcept SystemExit:\n    pass\n"
        f"print('LOADED', sorted(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    return ast.literal_eval(out.rsplit("LOADED ", 1)[1])


def test_help_imports_nothing_heavy():
    assert _imported_after(["--help"]) == []
    assert _imported_after([]) == []  # the usage error, too


def test_a_command_imports_only_its_own_modules():
    loaded = _imported_after(["fuzz", "--help"])
    assert "obu_service.pipeline" not in loaded and "link_emulator.cli" not in loaded
    assert "link_emulator.cli" not in _imported_after(["obu", "--help"])


def test_named_command():
    assert _named_command(["eval", "--seed", "1"]) == ["eval"]
    assert _named_command(["--help"]) == [] and _named_command(["evl"]) == []
    assert _named_command(["-h", "chaos", "run", "x.yaml"]) == ["chaos"]


def _options(parser, name: str) -> list[tuple]:
    """(flags, dest, default, choices) of every option of subcommand ``name``."""
    sub = next(a for a in parser._actions if a.dest == "command").choices[name]
    return [(tuple(a.option_strings), a.dest, a.default, tuple(a.choices or ())) for a in sub._actions]


@pytest.mark.parametrize("name", sorted(SUBCOMMANDS))
def test_a_command_parsed_alone_has_the_options_of_the_full_parser(name):
    assert _options(build_parser([name]), name) == _options(build_parser(), name)
    assert len(_options(build_parser([name]), name)) > 1  # more than --help


def test_the_services_import_no_image_library_for_their_simulated_sources():
    """OpenCV and ONNX Runtime load only for an image source (``--source camera|video``): not at every RSU and
    OBU start (OpenCV alone is ~15 ms of an RSU's start-up, whose target is ready within 1 s)."""
    code = ("import sys\nimport rsu_service.node, obu_service.node\n"
            "print('LOADED', sorted(m for m in ('cv2', 'onnxruntime') if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert ast.literal_eval(out.rsplit("LOADED ", 1)[1]) == []
