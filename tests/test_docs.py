"""The documentation: a short README.md, and docs/ built as an MkDocs site with --strict.

mkdocs.yml turns a page left out of the nav, a link to a missing page or file,
a missing anchor and an absolute link into warnings, so --strict fails on each.
The link check below covers README.md too, which is not part of the site.
"""
import importlib.util
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README_MAX_LINES = 250

_FENCE = re.compile(r"^\s*```.*?^\s*```", re.S | re.M)
_CODE_SPAN = re.compile(r"`[^`\n]*`")
_LINK = re.compile(r"!?\[[^\]\n]*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")


def _relative_links(path: Path) -> list[str]:
    """Targets of the Markdown links and images in `path` that point into the repository."""
    text = _CODE_SPAN.sub("", _FENCE.sub("", path.read_text()))
    targets = []
    for target in _LINK.findall(text):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target) or target.startswith("#"):
            continue  # http:, mailto: ... (README.md has none: checked below) or an anchor on the page
        targets.append(target)
    return targets


def _doc_pages() -> list[Path]:
    return sorted((ROOT / "docs").glob("*.md"))


def test_readme_is_short():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= README_MAX_LINES, f"README.md has {n} lines (at most {README_MAX_LINES}): move detail to docs/"


def test_readme_links_stay_in_the_repository():
    text = _CODE_SPAN.sub("", _FENCE.sub("", (ROOT / "README.md").read_text()))
    outside = [t for t in _LINK.findall(text) if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:|/", t)]
    assert not outside, f"README.md links outside the repository: {outside}"


@pytest.mark.parametrize("page", [ROOT / "README.md", *_doc_pages()], ids=lambda p: p.relative_to(ROOT).as_posix())
def test_relative_links_point_to_existing_files(page: Path):
    missing = []
    for target in _relative_links(page):
        file = target.split("#", 1)[0]
        if file and not (page.parent / file).exists():
            missing.append(target)
    assert not missing, f"{page.relative_to(ROOT)} links to files that do not exist: {missing}"


def test_index_is_the_readme():
    """docs/index.md is README.md with `](docs/` links made relative to docs/.

    Regenerate it with: sed 's|](docs/|](|g' README.md > docs/index.md
    """
    readme = (ROOT / "README.md").read_text()
    assert (ROOT / "docs" / "index.md").read_text() == readme.replace("](docs/", "]("), (
        "docs/index.md differs from README.md: sed 's|](docs/|](|g' README.md > docs/index.md"
    )


def test_mkdocs_build_strict(tmp_path: Path):
    if importlib.util.find_spec("mkdocs") is None:
        pytest.skip("mkdocs is not installed (pip install -e '.[test]')")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert (tmp_path / "site" / "index.html").is_file()
