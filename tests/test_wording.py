"""Verdict words in the results prose are backed by a published test (docs/analysis-plan.md, section 7).

Every sentence of the pages in :data:`PAGES` that holds a verdict word ("better", "worse", "faster",
"slower", "safer", "safe", "leans") must be listed in ``tests/data/verdict_words.toml``, either with
the published results that support it (results folder, condition, measure, verdict), which are
checked against that folder's ``summary.csv``, or as a use that is not a verdict on a coached
condition, with the reason. Generated blocks (between ``<!-- ...: begin`` and ``<!-- ...: end -->``
markers) and code blocks are skipped: their verdicts come from summary.csv itself.
"""

from __future__ import annotations

import csv
import re
from functools import cache
from pathlib import Path

import pytest
import tomllib

ROOT = Path(__file__).resolve().parents[1]
PAGES = ("docs/index.md", "docs/results/README.md", "docs/rescue.md")
WORDS = re.compile(r"\b(better|worse|faster|slower|safer|safe|leans?)\b", re.IGNORECASE)
LISTING = Path(__file__).parent / "data" / "verdict_words.toml"


def _prose(text: str) -> str:
    """The page without code blocks and generated blocks."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    text = re.sub(r"<!-- [\w ]+: begin.*?<!-- [\w ]+: end -->", "", text, flags=re.S)
    return "\n".join(line for line in text.splitlines() if not line.startswith("    "))  # indented code


def _units(text: str) -> list[str]:
    """Sentences of the prose, and table rows, with whitespace and emphasis normalized."""
    out = []
    for block in re.split(r"\n\s*\n", _prose(text)):
        lines = block.splitlines()
        rows = [line for line in lines if line.startswith("|")]
        out += rows
        flat = " ".join(line for line in lines if not line.startswith("|"))
        flat = re.sub(r"\s+", " ", flat.replace("**", ""))
        out += [s.strip() for s in re.split(r"(?<=[.!?:])\s+(?=[A-Z(`*-])", flat) if s.strip()]
    return out


def _normalize(text: str) -> str:
    return re.sub(r"\s+", " ", text.replace("**", "")).strip()


@cache
def _listing() -> list[dict]:
    return tomllib.loads(LISTING.read_text())["use"]


@cache
def _summary(folder: str) -> dict[tuple[str, str], dict[str, str]]:
    with open(ROOT / "docs" / "results" / folder / "summary.csv", newline="") as fh:
        return {(r["condition"], r["metric"]): r for r in csv.DictReader(fh)}


def _occurrences() -> list[tuple[str, str]]:
    found = []
    for page in PAGES:
        for unit in _units((ROOT / page).read_text()):
            if WORDS.search(unit):
                found.append((page, unit))
    return found


def test_every_verdict_word_is_listed():
    unlisted = []
    for page, unit in _occurrences():
        entries = [e for e in _listing() if e["page"] == page and _normalize(e["quote"]) in unit]
        covered = {w.lower() for e in entries for w in WORDS.findall(e["quote"])}
        words = {w.lower() for w in WORDS.findall(unit)}
        if not words <= covered:
            unlisted.append(f"{page}: {sorted(words - covered)} in: {unit[:200]}")
    assert not unlisted, "verdict words without an entry in tests/data/verdict_words.toml:\n" + "\n".join(
        unlisted
    )


def test_every_listed_use_is_still_on_its_page():
    stale = [
        f"{e['page']}: {e['quote']!r}"
        for e in _listing()
        if not any(_normalize(e["quote"]) in unit for p, unit in _occurrences() if p == e["page"])
    ]
    assert not stale, "entries whose sentence is gone (remove or update them):\n" + "\n".join(stale)


@pytest.mark.parametrize("entry", _listing(), ids=lambda e: f"{e['page']}:{e['quote'][:40]}")
def test_each_listed_verdict_is_the_published_one(entry: dict):
    assert WORDS.search(entry["quote"]), "a listed quote must hold a verdict word"
    supports = entry.get("support", [])
    assert bool(supports) != bool(entry.get("not_a_verdict")), (
        "each entry either names its supporting results or says why it is not a verdict"
    )
    for s in supports:
        row = _summary(s["folder"]).get((s["condition"], s["metric"]))
        assert row is not None, f"{s['folder']}: no summary row for {s['condition']}/{s['metric']}"
        assert row["verdict"] == s["verdict"], (
            f"{s['folder']} {s['condition']}/{s['metric']}: the published verdict is {row['verdict']!r}, "
            f"the prose says {s['verdict']!r}"
        )


def test_the_checker_catches_an_unlisted_verdict():
    text = "Intro.\n\nThe coach makes the agent faster. It is better.\n\n<!-- x: begin -->\nworse\n<!-- x: end -->\n"
    units = [u for u in _units(text) if WORDS.search(u)]
    assert units == ["The coach makes the agent faster.", "It is better."]
