"""One output option on every command, help that names what values are, -v anywhere."""

from __future__ import annotations

from typing import Any

import pytest
import typer
from typer.testing import CliRunner

from station.cli import _verbosity_first, app

NO_DATA = {"version"}
"""Prints the version string and nothing a machine parses."""
ROWS = {"history", "query", "stats", "recipes"}
"""Commands whose data are rows, so CSV too."""


def _commands() -> dict[str, Any]:
    """Every command, sub-commands by their full name (typer's own command classes)."""
    group = typer.main.get_command(app)
    found: dict[str, Any] = {}
    for name, command in getattr(group, "commands", {}).items():
        if hasattr(command, "commands"):
            found.update({f"{name} {sub}": c for sub, c in command.commands.items()})
        else:
            found[name] = command
    return found


def test_every_command_that_prints_data_has_one_output_option() -> None:
    commands = _commands()
    assert {"calibrate", "report", "sim record", "sim unit"} <= commands.keys()
    for name, command in commands.items():
        if name in NO_DATA:
            continue
        options = {opt: p for p in command.params for opt in getattr(p, "opts", ())}
        assert "--json" in options and "--format" in options, name
        choices = set(options["--format"].type_descriptor.choices or ())
        expected = {"table", "json", "csv"} if name in ROWS else {"table", "json"}
        assert {str(getattr(c, "value", c)) for c in choices} == expected, name


@pytest.mark.parametrize("name", sorted(set(_commands()) - NO_DATA))
def test_help_names_what_values_are_not_their_python_types(name: str) -> None:
    shown = CliRunner().invoke(app, [*name.split(), "--help"], env={"COLUMNS": "200"})
    assert shown.exit_code == 0, shown.output
    for python_type in ("<str>", "<int>", "<float>", "<bool>", "<path>", "{serial}"):
        assert python_type not in shown.output, (name, python_type)


def test_verbosity_is_read_wherever_the_operator_types_it() -> None:
    assert _verbosity_first(["calibrate", "SN123", "-v"]) == ["-v", "calibrate", "SN123"]
    assert _verbosity_first(["history", "-vv", "SN1", "--json"]) == [
        "-vv", "history", "SN1", "--json"]
    assert _verbosity_first(["calibrate", "SN1", "--json", "--verbose"]) == [
        "--verbose", "calibrate", "SN1", "--json"]
    # A value that looks like it stays the option's value; after "--" nothing moves.
    assert _verbosity_first(["recalibrate", "SN1", "--reason", "-v"]) == [
        "recalibrate", "SN1", "--reason", "-v"]
    assert _verbosity_first(["analyze", "--", "-v"]) == ["analyze", "--", "-v"]
