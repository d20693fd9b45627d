"""The front page and the docs: README's quick start runs as written (the fenced block under "## Quick start",
verbatim, in a fresh interpreter with deprecation warnings as errors), README stays short, and every page of the
docs site that the README links exists."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def quick_start(text: str) -> str:
    """The first ```python block after the "## Quick start" heading, as written."""
    section = text.split("\n## Quick start\n", 1)[1].split("\n## ", 1)[0]
    match = re.search(r"^```python\n(.*?)^```$", section, re.S | re.M)
    assert match, "no ```python block under ## Quick start"
    return match.group(1)


def test_quick_start_runs_verbatim(tmp_path):
    code = quick_start(README.read_text(encoding="utf-8"))
    assert len(code.splitlines()) <= 25
    script = tmp_path / "quick_start.py"
    script.write_text(code, encoding="utf-8")
    run = subprocess.run(
        [sys.executable, "-W", "error::DeprecationWarning", str(script)],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr
    assert "stereo: valid on" in run.stdout and "frame 3:" in run.stdout


def test_quick_start_extraction_fails_on_a_broken_block():
    broken = "# x\n\n## Quick start\n\n```python\nprint(undefined_name)\n```\n\n## Next\n"
    code = quick_start(broken)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.returncode != 0 and "NameError" in run.stderr


def test_readme_is_short():
    assert len(README.read_text(encoding="utf-8").splitlines()) <= 200


def test_readme_links_resolve():
    text = README.read_text(encoding="utf-8")
    targets = {t.split("#", 1)[0] for t in re.findall(r"\]\(([^)\s]+)\)", text) if "://" not in t}
    missing = sorted(t for t in targets if t and not (ROOT / t).exists())
    assert not missing, missing


def test_project_files_exist():
    for name in ("LICENSE", "CITATION.cff", "CHANGELOG.md", "CONTRIBUTING.md", "mkdocs.yml"):
        assert (ROOT / name).is_file(), name
