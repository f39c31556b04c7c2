"""The README is a front door and docs/ a reference (issue 62): sizes, words, links.

- README.md at most 120 lines; the reference pages (every docs/*.md but the experiment log,
  docs/log.md) at most 1,500 lines together;
- no "night", "today", "this morning" or "evening" in the README or a reference page (dates and times
  of day belong in the log, and a table's "Measured on" line);
- every relative link in README.md and docs/*.md names a file that exists and, with ``#anchor``, a
  heading of that file (GitHub's anchors).

Tables (every row with its header's cell count) and published numbers: tests/scripts/test_publish_tables.py.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
LOG = REPO / "docs" / "log.md"
REFERENCE = sorted(p for p in (REPO / "docs").glob("*.md") if p != LOG)
FORBIDDEN = re.compile(r"\b(night|today|this morning|evening)\b", re.I)
LINK = re.compile(r"\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.S | re.M)


def test_the_readme_is_short_and_the_reference_pages_together_too():
    readme = len(README.read_text().splitlines())
    assert readme <= 120, f"README.md has {readme} lines (at most 120)"
    sizes = {p.name: len(p.read_text().splitlines()) for p in REFERENCE}
    assert sum(sizes.values()) <= 1500, (
        f"reference pages {sum(sizes.values())} lines (at most 1,500): {sizes}"
    )
    assert LOG.is_file(), "the experiment log docs/log.md"


@pytest.mark.parametrize("page", [README, *REFERENCE], ids=lambda p: p.name)
def test_no_time_of_day_in_the_readme_or_a_reference_page(page):
    hits = [
        f"{page.name}:{i}: {line.strip()}"
        for i, line in enumerate(page.read_text().splitlines(), 1)
        if FORBIDDEN.search(line)
    ]
    assert not hits, "a time of day belongs in docs/log.md:\n" + "\n".join(hits)


def test_the_word_check_is_whole_words_and_any_case():
    assert FORBIDDEN.search("measured last Night") and FORBIDDEN.search("as of TODAY.")
    assert FORBIDDEN.search("done this morning") and FORBIDDEN.search("(evening)")
    assert not FORBIDDEN.search("nightly builds, eveningly, todays") and not FORBIDDEN.search("morning")


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = FENCE.sub("", page.read_text())
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.M)}


@pytest.mark.parametrize("page", [README, *REFERENCE, LOG], ids=lambda p: p.name)
def test_every_relative_link_resolves(page):
    problems = []
    for target in LINK.findall(FENCE.sub("", page.read_text())):
        if "://" in target or target.startswith("mailto:"):
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        if not dest.exists():
            problems.append(
                f"{target}: no file {dest.relative_to(REPO) if dest.is_relative_to(REPO) else dest}"
            )
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            problems.append(f"{target}: no heading with that anchor in {dest.name}")
    assert not problems, f"{page.name}:\n" + "\n".join(problems)


def test_the_anchor_rule_is_githubs():
    assert slug("Levels (`--scenes levelK:N`)") == "levels---scenes-levelkn"
    assert slug("2026-12-03: Why the bend's gap is 1.8-2.2 m") == "2026-12-03-why-the-bends-gap-is-18-22-m"
