"""Every relative link in README.md and docs/ points to an existing file and, when it names an anchor,
to a heading of that file (GitHub's anchor rules: lower case, punctuation dropped, spaces to
hyphens, repeated headings numbered -1, -2, ...)."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md"))]
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(([^()\s]+)\)")


def prose(text: str) -> str:
    """The text outside fenced code blocks and inline code spans (links there are not links)."""
    out, fence = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        if not fence:
            out.append(re.sub(r"`[^`]*`", "``", line))
    return "\n".join(out)


def slug(heading: str) -> str:
    text = heading.strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)  # \w keeps letters, digits and '_' (also non-ASCII letters)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    result = set()
    fence = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fence = not fence
            continue
        m = None if fence else re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
        if m:
            base = slug(m.group(1))
            n = seen.get(base, 0)
            seen[base] = n + 1
            result.add(base if n == 0 else f"{base}-{n}")
    return result


def test_slug_follows_github_rules() -> None:
    assert slug("Running live: params, shutdown, loss") == "running-live-params-shutdown-loss"
    assert slug("Making a graph, and the TLL particle filter (`tll_pf`)") == (
        "making-a-graph-and-the-tll-particle-filter-tll_pf")
    assert slug("Replay bags offline: `indoor-loc run`") == "replay-bags-offline-indoor-loc-run"


def test_docs_pages_exist() -> None:
    assert (ROOT / "docs" / "nodes.md").is_file()
    assert len(PAGES) > 5


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_relative_links_resolve(page: Path) -> None:
    text = prose(page.read_text(encoding="utf-8"))
    bad = []
    for target in LINK.findall(text):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        path_part, _, anchor = target.partition("#")
        dest = (page.parent / path_part).resolve() if path_part else page
        if not dest.exists():
            bad.append(f"{target}: no file {dest}")
            continue
        if anchor and (dest.suffix != ".md" or anchor not in anchors(dest)):
            bad.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not bad, "\n".join(bad)


def test_every_docs_page_is_reachable_from_the_readme() -> None:
    """A page nobody links to is lost to readers: each docs page is reached from README.md."""
    reached, todo = set(), [ROOT / "README.md"]
    while todo:
        page = todo.pop()
        if page in reached:
            continue
        reached.add(page)
        for target in LINK.findall(prose(page.read_text(encoding="utf-8"))):
            path_part = target.partition("#")[0]
            dest = (page.parent / path_part).resolve()
            if path_part and dest.suffix == ".md" and dest.is_file():
                todo.append(dest)
    orphans = [str(p.relative_to(ROOT)) for p in PAGES if p.resolve() not in reached]
    assert not orphans, f"not linked from README.md (directly or through a linked page): {orphans}"


def test_readme_results_figures_are_on_their_pages() -> None:
    """The README's Results section summarises the docs pages: each block (a bold title, its links
    and its table) may only state decimal figures found on the pages it links to, so a figure
    updated there and not in the summary (or mistyped) shows up."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert "\n## Results\n" in readme
    section = readme.split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.split(r"\n(?=\*\*)", section)[1:]
    assert len(blocks) >= 4
    missing = []
    for block in blocks:
        pages = {(ROOT / t.partition("#")[0]).resolve() for t in LINK.findall(prose(block))
                 if t.partition("#")[0].endswith(".md")}
        assert pages, f"a Results block links no page: {block[:60]!r}"
        text = "\n".join(p.read_text(encoding="utf-8") for p in pages)
        for fig in sorted(set(re.findall(r"(?<![\w.])\d+\.\d+(?![\w.])", block))):
            if not re.search(rf"(?<![\w.]){re.escape(fig)}(?![\w.])", text):
                missing.append(f"{fig} (block {block.splitlines()[0][:50]!r})")
    assert not missing, "figures of the README's Results not on the pages they link to:\n" + "\n".join(missing)
