"""The repository stands alone: every file a docstring, help text or doc cites is in it."""

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXT_SUFFIXES = {".py", ".md", ".toml", ".txt", ".cfg"}
SCANNED = ["README.md", "pyproject.toml", "ivc", "docs", "tests", "benchmarks", "sample_data", ".ci"]
#: a path inside the repository named in prose: docs/lut.md, ivc/table/lookup.py, sample_data/README.md
REPO_PATH = re.compile(r"(?<![\w./-])((?:docs|ivc|tests|benchmarks|sample_data|\.ci)/[\w./-]*\w)")
#: a bare Markdown file name: MATH.md, lut-format.md
BARE_MD = re.compile(r"(?<![\w./-])([\w-]+\.md)\b")
#: a Markdown link target: [text](target)
LINK = re.compile(r"\]\(([^)\s#]+)(?:#[^)]*)?\)")
#: what the repository must not cite: private references and "the seed" for a source paper
PRIVATE_FILES = re.compile(r"(?<![\w/])MATH\.md|(?<![\w/.])(?:notes|spec|seeds)/\w")
PAPER_AS_SEED = re.compile(r"\bseed 00\d|\bthe seed'?s?\b|\bseed's\b", re.IGNORECASE)
#: a random-number seed or a solver's starting point is not a paper
SEED_WORDS = re.compile(r"random seed|solver's seed|seed (?:pose|value|the)|seeds? the|at the seed|"
                        r"the seed (?:pose|solution|of the solve)", re.IGNORECASE)


def _files():
    for entry in SCANNED:
        path = ROOT / entry
        if path.is_file():
            yield path
        elif path.is_dir():
            for file in sorted(path.rglob("*")):
                if file.is_file() and (file.suffix in TEXT_SUFFIXES or file.name == "run") \
                        and "__pycache__" not in file.parts:
                    yield file


#: the pages the documentation build makes itself (docs/hooks/generated.py)
GENERATED_PAGES = {"api.md", "gallery.md"}


def _exists(name: str, near: Path) -> bool:
    name = name.rstrip(".,:;")
    if name in GENERATED_PAGES:
        return True
    candidates = [ROOT / name, near.parent / name, ROOT / "docs" / name]
    return any(c.exists() for c in candidates) or any(c.with_suffix("").exists() for c in candidates)


def test_every_cited_file_is_in_the_repository():
    if not (ROOT / "ivc").is_dir():
        pytest.skip("not a source checkout")
    missing = []
    for file in _files():
        if file.name == "test_docs.py":
            continue
        for number, line in enumerate(file.read_text(errors="replace").splitlines(), 1):
            names = REPO_PATH.findall(line) + BARE_MD.findall(line)
            if file.suffix == ".md":
                names += [t for t in LINK.findall(line) if not re.match(r"[a-z]+:", t)]
            for name in names:
                if not _exists(name, file):
                    missing.append(f"{file.relative_to(ROOT)}:{number}: {name}")
    assert not missing, "cited but not in the repository:\n" + "\n".join(missing)


def test_nothing_cites_the_private_references():
    found = []
    for file in _files():
        if file.name == "test_docs.py":
            continue
        for number, line in enumerate(file.read_text(errors="replace").splitlines(), 1):
            if PRIVATE_FILES.search(line) or PAPER_AS_SEED.search(SEED_WORDS.sub("", line)):
                found.append(f"{file.relative_to(ROOT)}:{number}: {line.strip()[:100]}")
    assert not found, "cite the papers by author and year (docs/references.md), equations by docs/math.md:\n" + \
        "\n".join(found)


def test_the_checker_catches_a_missing_file(tmp_path):
    assert _exists("docs/math.md", ROOT / "README.md")
    assert not _exists("docs/lut-format.md", ROOT / "README.md")
    assert BARE_MD.findall("see MATH.md §2") == ["MATH.md"]
    assert PAPER_AS_SEED.search("the seed's Table 24") and not PAPER_AS_SEED.search(SEED_WORDS.sub("", "a random seed"))
    assert PRIVATE_FILES.search("see MATH.md §2") and not PRIVATE_FILES.search("see docs/math.md §2")
