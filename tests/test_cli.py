"""Every ``upright`` command has ``--help`` and a registered, importable module."""

from __future__ import annotations

import importlib

import pytest

from host.cli import main as cli


@pytest.mark.parametrize("name", sorted(cli.COMMANDS))
def test_every_command_has_help(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    importlib.import_module(cli.COMMANDS[name][0])  # the module exists
    with pytest.raises(SystemExit) as exc:
        cli.main([name, "--help"])
    assert exc.value.code == 0
    assert "usage: upright " + name in capsys.readouterr().out


def test_no_command_prints_help(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main([]) == 2
    assert "COMMAND" in capsys.readouterr().out
