"""The man pages in man/ never drift from `--help`: every registered command (walked through
``cli.commands``, so new commands are covered) has a page naming each option `--help` lists and
holding the first line of its help text."""
from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner

from splatk_cli.main import cli

MAN = Path(__file__).resolve().parents[2] / "man"
REGENERATE = "regenerate the man pages: pip install click-man && python scripts/gen_man.py (then commit man/)"
OPTION = re.compile(r"(?<![\w-])(--?[A-Za-z0-9][\w-]*)")


def all_commands(group: click.Group = cli, path: tuple[str, ...] = ("splatk",)):
    yield path, group
    for name, cmd in getattr(group, "commands", {}).items():
        if cmd.hidden:
            continue
        if isinstance(cmd, click.Group):
            yield from all_commands(cmd, path + (name,))
        else:
            yield path + (name,), cmd


COMMANDS = list(all_commands())


def roff_to_text(page: str) -> str:
    """Enough roff decoding to search the text: escapes and font changes removed."""
    return page.replace(r"\-", "-").replace(r"\fB", "").replace(r"\fP", "").replace(r"\fI", "").replace(r"\fR", "")


def help_of(path: tuple[str, ...]) -> tuple[list[str], str]:
    """(option names, first line of the description) as `splatk ... --help` prints them."""
    res = CliRunner().invoke(cli, [*path[1:], "--help"], terminal_width=200)
    assert res.exit_code == 0, res.output
    lines = res.output.splitlines()
    start = lines.index("Options:")
    options = []
    for line in lines[start + 1:]:
        if not line.startswith("  -"):
            continue  # a wrapped description, or the next section
        first_column = re.split(r"\s{2,}", line.strip())[0]
        options += [o for o in OPTION.findall(first_column) if o not in ("-h", "--help")]
    description = [ln.strip() for ln in lines[1:start] if ln.strip()]
    return options, description[0] if description else ""


def test_every_command_has_a_page():
    missing = [f"{'-'.join(p)}.1" for p, _ in COMMANDS if not (MAN / f"{'-'.join(p)}.1").is_file()]
    assert not missing, f"no man page for {', '.join(missing)}: {REGENERATE}"


@pytest.mark.parametrize("path", [p for p, _ in COMMANDS], ids=[" ".join(p) for p, _ in COMMANDS])
def test_page_matches_help(path):
    page = MAN / f"{'-'.join(path)}.1"
    assert page.is_file(), f"{page} is missing: {REGENERATE}"
    text = roff_to_text(page.read_text())
    options, first_line = help_of(path)
    assert options or path == ("splatk",), "parsed no options from --help"
    stale = [o for o in options if not re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", text)]
    assert not stale, f"{page.name} lacks {', '.join(stale)}: {REGENERATE}"
    squeeze = lambda s: re.sub(r"\s+", "", s)  # noqa: E731 - --help wraps lines, the page does not
    assert squeeze(first_line) in squeeze(text), f"{page.name} lacks {first_line!r}: {REGENERATE}"
    assert f'.TH "{" ".join(path).upper()}"' in page.read_text(), f"{page.name} is for another command: {REGENERATE}"
