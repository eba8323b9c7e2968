"""The docs and code cite sections of docs/RESULTS.md that exist: a section that left RESULTS
for the diary is cited as RESULTS@bf0c7b2 (README), so no citation points at nothing."""
import pathlib
import re
import subprocess

ROOT = pathlib.Path(__file__).resolve().parents[1]
CITE = re.compile(r'(?:docs/)?RESULTS(?:\.md)?(?:, *| +)"([^"]+)"')


def _norm(text: str) -> str:
    """Whitespace, line breaks and the comment / list marks a wrapped title picks up."""
    return re.sub(r"\s+", " ", re.sub(r"\n\s*(#|\*|//)?\s*", " ", text)).strip().lower()


def stale_citations(root: pathlib.Path) -> list[str]:
    results = _norm((root / "docs" / "RESULTS.md").read_text())
    files = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True,
                           check=True).stdout.split()
    bad = []
    for f in files:
        if f == "docs/RESULTS.md" or not f.endswith((".py", ".md", ".sh", ".toml")):
            continue
        text = (root / f).read_text()
        for m in CITE.finditer(text):
            if _norm(m.group(1)).rstrip(".,;:") not in results:
                bad.append(f"{f}:{text[:m.start()].count(chr(10)) + 1}: {m.group(1)!r}")
    return bad


def test_results_citations_name_existing_sections():
    assert stale_citations(ROOT) == []


def test_a_citation_of_a_missing_section_is_found(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "RESULTS.md").write_text("## The oracle\n\ntext\n")
    q = '"'  # written apart, so that this file holds no citation itself
    (tmp_path / "a.py").write_text(f'# see docs/RESULTS.md, {q}The oracle{q} and RESULTS, '
                                   f'{q}Gone\n# away{q}; RESULTS@bf0c7b2, {q}Old{q} is the '
                                   'diary\n')
    subprocess.run(["git", "init", "-q"], cwd=tmp_path, check=True)
    subprocess.run(["git", "add", "."], cwd=tmp_path, check=True)
    assert [b.split(": ", 1)[1] for b in stale_citations(tmp_path)] == ["'Gone\\n# away'"]
