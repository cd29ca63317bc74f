"""Every command's ``--help`` renders (argparse %-formats help strings: a bare % crashes it),
the commands found from the parser itself, nested ones (``tables build``) included."""

from __future__ import annotations

import argparse

import pytest

from ddh_vsensor.cli.main import SUBCOMMANDS, build_parser, main


def _commands(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()
              ) -> list[tuple[str, ...]]:
    out = [prefix]
    for action in parser._actions:                     # noqa: SLF001 - argparse has no API
        if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
            for name, sub in action.choices.items():
                out += _commands(sub, (*prefix, name))
    return out


COMMANDS = _commands(build_parser())


def test_every_registered_module_is_a_command() -> None:
    assert set(SUBCOMMANDS) <= {c[0] for c in COMMANDS if c}
    assert ("tables", "build") in COMMANDS         # nested commands are found too


def test_simulate_fleet_reaches_the_fleet_simulator(capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(["-q", "simulate", "fleet", "--help"])
    assert exit_.value.code == 0
    assert "--machines" in capsys.readouterr().out


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: " ".join(c) or "ddh-vsensor")
def test_help_renders(command: tuple[str, ...], capsys) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([*command, "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: ddh-vsensor") and "options:" in out
