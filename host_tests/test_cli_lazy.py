"""The command line defines the arguments of the verb it runs only (cli._parser): the
other verbs' definitions import their modules (trace, tables, campaigns), which `magcal
fit` would otherwise pay for before it starts."""

from __future__ import annotations

import subprocess
import sys

import pytest

from generator import cli

HEAVY = ("generator.verbs.trace", "generator.verbs.table", "generator.campaign.check",
         "generator.campaign.plan", "generator.flight.table_host")


def test_the_fit_parser_imports_no_other_verbs_modules():
    code = ("import sys, generator.cli as c; c._parser(['fit', 'u', 'd', '-o', 'x']); "
            f"print([m for m in {HEAVY!r} if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]", r.stdout
    # and the full parser does import them (the check above can fail)
    code_full = ("import sys, generator.cli as c; c.build_parser(); "
                 f"print([m for m in {HEAVY!r} if m in sys.modules])")
    r = subprocess.run([sys.executable, "-c", code_full], capture_output=True, text=True)
    assert "generator.verbs.trace" in r.stdout


@pytest.mark.parametrize("verb", sorted(cli.VERBS))
def test_each_verbs_arguments_are_those_of_the_full_parser(verb):
    """A verb's own parser has exactly the options the full parser gives it."""
    def options(parser):
        sub = next(a for a in parser._actions if a.dest == "verb")
        return sorted(tuple(a.option_strings) or (a.dest,)
                      for a in sub.choices[verb]._actions)
    assert options(cli._parser([verb])) == options(cli.build_parser())


def test_global_options_and_misspelt_verbs_still_parse():
    assert cli.main(["--debug", "fit"]) == 2          # the verb's own required arguments
    assert cli.main(["nosuchverb"]) == 2
