"""README.md opens with the two commands, and .ci/run runs the test command it gives."""
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _readme_commands() -> list[str]:
    text = (ROOT / "README.md").read_text()
    block = text.split("```bash", 1)[1].split("```", 1)[0]
    return [ln.strip() for ln in block.splitlines() if ln.strip() and not ln.strip().startswith("#")]


def test_readme_opens_with_run_and_test_commands():
    cmds = _readme_commands()
    assert len(cmds) == 2
    assert cmds[0].startswith("./deploy/setup.sh && ") and "undream " in cmds[0]
    assert cmds[1].startswith("./deploy/setup.sh && ") and "pytest" in cmds[1]


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text().splitlines()
    assert _readme_commands()[1] in [ln.strip() for ln in ci if not ln.strip().startswith("#")]
