"""The docs' links hold: every relative link and ``#anchor`` in the README, CONTRIBUTING, the
changelog and ``docs/*.md`` resolves to an existing file and heading, and every place in the
repository that cites ``docs/DESIGN.md §N`` or a section of DESIGN or RESULTS by its quoted name
names one that exists.

Anchors are GitHub's: a heading's text without its markup, lower-cased, every character but
letters, digits, ``_``, ``-`` and spaces dropped, spaces turned into ``-``; a repeated heading
gets ``-1``, ``-2``, ... in turn.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
DESIGN = REPO / "docs" / "DESIGN.md"
RESULTS = REPO / "docs" / "RESULTS.md"
#: Folders never searched for citations: tools, data and build output.
SKIP_DIRS = {"data", "out", "build", "dist", "__pycache__", "node_modules"}

FENCE = re.compile(r"^[ \t]*(```|~~~).*?^[ \t]*\1[ \t]*$", re.S | re.M)
INLINE_CODE = re.compile(r"(`+)(.+?)\1", re.S)
HEADING = re.compile(r"^(#{1,6})[ \t]+(.+?)[ \t]*#*[ \t]*$", re.M)
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE = re.compile(r"^[ \t]{0,3}\[[^\]]+\]:[ \t]*<?(\S+?)>?(?:[ \t]+\"[^\"]*\")?[ \t]*$", re.M)
HTML_ANCHOR = re.compile(r"<a\s+(?:id|name)=\"([^\"]+)\"", re.I)
BOLD = re.compile(r"\*\*(.+?)\*\*", re.S)
#: ``DESIGN.md §7``, ``DESIGN.md §4, §7``, ``DESIGN.md §5-§9``: the numbers cited.
SECTION_CITE = re.compile(
    r"DESIGN(?:\.md)?,?[ \t]+(§[ \t]?\d+(?:[ \t]*(?:,|-|–|and)[ \t]*§[ \t]?\d+)*)"
)
#: A section cited by its quoted name after DESIGN or RESULTS (and a section number): the name.
NAME_CITE = re.compile(
    r"\b(DESIGN|RESULTS)(?:\.md)?(?:[ \t]*§[ \t]?\d+)?[ \t]*[,(][ \t]*\(?\"([^\"\n]+)\""
)


def _docs() -> list[Path]:
    root = [REPO / name for name in ("README.md", "CONTRIBUTING.md", "CHANGELOG.md")]
    return [p for p in root if p.exists()] + sorted((REPO / "docs").glob("*.md"))


def _prose(text: str) -> str:
    """The text without fenced code blocks (their lines kept empty, so line numbers hold)."""
    return FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), text)


def _heading_text(raw: str) -> str:
    """A heading's text as rendered: code spans, links and emphasis reduced to their text."""
    text = INLINE_CODE.sub(lambda m: m.group(2), raw)
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", text)
    text = re.sub(r"<[^>]+>", "", text)
    return text.replace("*", "").strip()


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's rendered text."""
    text = re.sub(r"[^\w\- ]", "", heading.lower())
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """Every anchor a Markdown file defines: its headings' slugs and explicit HTML anchors."""
    text = _prose(path.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set(HTML_ANCHOR.findall(text))
    for m in HEADING.finditer(text):
        base = slug(_heading_text(m.group(2)))
        n = seen.get(base, 0)
        seen[base] = n + 1
        out.add(base if n == 0 else f"{base}-{n}")
    return out


def _links(text: str) -> list[tuple[int, str]]:
    """(line, target) of every inline and reference link outside code."""
    text = _prose(text)
    text = INLINE_CODE.sub(lambda m: " " * len(m.group(0)), text)
    found = [(m.start(), m.group(1)) for m in LINK.finditer(text)]
    found += [(m.start(), m.group(1)) for m in REFERENCE.finditer(text)]
    return [(text.count("\n", 0, pos) + 1, target) for pos, target in sorted(found)]


def broken_links(path: Path) -> list[str]:
    """``file:line: target (why)`` for every relative link of `path` that does not resolve."""
    problems = []
    for line, target in _links(path.read_text(encoding="utf-8")):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):
            continue  # http:, https:, mailto: and other schemes are not checked here
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        where = f"{path.relative_to(REPO)}:{line}: {target}"
        if not dest.exists():
            problems.append(f"{where} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{where} (no heading with that anchor in {dest.name})")
        elif anchor and dest.suffix != ".md":
            problems.append(f"{where} (an anchor into a file that is not Markdown)")
    return problems


def _citing_files() -> list[Path]:
    out = []
    for root, dirs, files in os.walk(REPO):
        dirs[:] = [
            d for d in dirs if not d.startswith(".") and d not in SKIP_DIRS and "egg-info" not in d
        ]
        out += [
            Path(root) / f
            for f in files
            if f.endswith((".py", ".md", ".toml")) or f in {"Makefile"}
        ]
    return sorted(out)


def _design_sections() -> set[int]:
    text = _prose(DESIGN.read_text(encoding="utf-8"))
    return {int(n) for n in re.findall(r"^## (\d+)\. ", text, re.M)}


def _names(path: Path) -> set[str]:
    """What a citation may name in `path`: its headings (without a section number) and, for
    DESIGN, the bold lead of a paragraph or bullet."""
    text = _prose(path.read_text(encoding="utf-8"))
    names = set()
    for m in HEADING.finditer(text):
        raw = m.group(2).strip()
        names.add(raw)
        names.add(re.sub(r"^\d+\.\s+", "", raw))
    if path == DESIGN:
        names |= {re.sub(r"[.:,]$", "", b.strip()) for b in BOLD.findall(text)}
    return names


def test_every_relative_link_and_anchor_of_the_docs_resolves() -> None:
    docs = _docs()
    assert REPO / "README.md" in docs and DESIGN in docs and RESULTS in docs
    problems = [p for doc in docs for p in broken_links(doc)]
    assert not problems, "broken links:\n" + "\n".join(problems)


def test_every_cited_design_section_number_exists() -> None:
    sections = _design_sections()
    assert sections == set(range(1, max(sections) + 1)), f"DESIGN's sections: {sorted(sections)}"
    problems = []
    for path in _citing_files():
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for m in SECTION_CITE.finditer(line):
                cited = {int(n) for n in re.findall(r"\d+", m.group(1))}
                if cited - sections:
                    problems.append(f"{path.relative_to(REPO)}:{lineno}: {m.group(0)}")
    assert not problems, "citations of DESIGN sections that do not exist:\n" + "\n".join(problems)


def test_every_section_cited_by_name_exists() -> None:
    names = {"DESIGN": _names(DESIGN), "RESULTS": _names(RESULTS)}
    problems = []
    for path in _citing_files():
        for lineno, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            for m in NAME_CITE.finditer(line):
                doc, name = m.group(1), m.group(2)
                if name not in names[doc]:
                    problems.append(f'{path.relative_to(REPO)}:{lineno}: {doc} "{name}"')
    assert not problems, "sections cited by a name no heading carries:\n" + "\n".join(problems)


GUIDE_ESTIMATORS = REPO / "docs" / "guide-estimators.md"
#: A row of the guide's list of built-in estimators: name, what it is, observes, extra.
ESTIMATOR_ROW = re.compile(r"^\| `([^`]+)`[^|]*\|.+\| `(rgbd?)` \| ([^|]+?) \|$", re.M)
CRUDE = REPO / "examples" / "crude-estimator"


def test_the_estimators_guide_lists_every_built_in_estimator_with_its_mode_and_extra() -> None:
    import tomllib

    from sim.episodes.registry import ENTRY_POINT_GROUP, ESTIMATORS, needs_depth

    section = GUIDE_ESTIMATORS.read_text(encoding="utf-8").split("## Built-in estimators", 1)[1]
    rows = {m[1]: (m[2], m[3]) for m in ESTIMATOR_ROW.finditer(section)}
    example = tomllib.loads((CRUDE / "pyproject.toml").read_text())
    installed = set(example["project"]["entry-points"][ENTRY_POINT_GROUP])  # crude, by make setup
    assert set(ESTIMATORS) | installed == set(rows), "not listed, or listed but not built in"
    extras = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    known = {f"`{name}`" for name in extras["optional-dependencies"]} | {"-"}
    for name, (mode, extra) in rows.items():
        assert mode == ("rgbd" if needs_depth(name) else "rgb"), name
        assert extra in known or (name in installed and "examples/crude-estimator" in extra), name
