"""The README's test command is the one CI runs: `.ci/run` holds it verbatim."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_test_command() -> str:
    text = (ROOT / "README.md").read_text()
    m = re.search(r"Run the tests:\s*```bash\n(.+?)\n```", text, re.S)
    assert m, "README.md has no `Run the tests:` code block"
    return m.group(1).strip()


def test_ci_runs_the_readme_test_command():
    command = _readme_test_command()
    assert "\n" not in command, "the README's test command is one line"
    assert "install_test_assets.sh" in command, \
        "the README's test command installs the LPIPS weights and the viewer test's browser"
    ci_lines = [ln.strip() for ln in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert command in ci_lines, f".ci/run does not run the README's test command {command!r}"
    assert not any("pytest" in ln for ln in ci_lines if ln != command and not ln.startswith("#")), \
        ".ci/run runs pytest besides the README's command"
