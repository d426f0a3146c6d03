"""Docs lint: the user-facing text describes the library as it is.

README.md, docs/, src/, bench/, examples/, tests/ and adapters/ must not speak of development
rounds or issue numbers, nor name paths of one machine (a temporary folder, a home folder); the
history belongs in CHANGELOG.md (not scanned) and in git. Each hit is reported as
``file:line: kind: match``.

The patterns are written so that this file's own source does not match them (the self-test's
examples are joined from two halves, and a bracketed letter keeps a literal path from matching
itself), so the file is scanned like every other one.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: What is scanned, relative to the repository root.
SCANNED = ("README.md", "docs", "src", "bench", "examples", "tests", "adapters")

#: Text files among them (pictures and binary test data are not read).
TEXT_SUFFIXES = {".md", ".py", ".txt", ".toml", ".cfg", ".ini", ".yml", ".yaml", ".json", ".sh"}

# A word that is part of a longer word or of an option name ("background", "--dense-stop") is
# not a hit: nothing word-like, no hyphen, dot, slash or tilde may stand right before it.
_START = r"(?<![\w./~-])"

PATTERNS: dict[str, re.Pattern[str]] = {
    # A development round by its number: the word stop or round, a space or hyphen, digits.
    "development round": re.compile(_START + r"(?:stops?|rounds?)[\s_-]?#?\d+\b", re.IGNORECASE),
    # A tracker number: the word issue, an optional hash, digits (a link to .../issues/N is fine).
    "issue number": re.compile(_START + r"issues?[\s-]?#?\d+\b", re.IGNORECASE),
    # A temporary, work or home folder of one machine. The bracketed letters keep these
    # expressions from matching their own source text.
    "machine path": re.compile(_START + r"(?:/tm[p]/[\w.-]|/wor[k]/|/roo[t]/|/hom[e]/\w|/User[s]/\w)"),
}


def _scanned_files() -> list[Path]:
    files: list[Path] = []
    for entry in SCANNED:
        path = ROOT / entry
        if path.is_file():
            files.append(path)
        elif path.is_dir():
            files.extend(
                p for p in sorted(path.rglob("*"))
                if p.is_file() and p.suffix in TEXT_SUFFIXES and "__pycache__" not in p.parts
            )
    return files


def _hits(text: str) -> list[tuple[int, str, str]]:
    """(line number, kind, matched text) of every pattern match in ``text``."""
    found = []
    for kind, pattern in PATTERNS.items():
        for match in pattern.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            found.append((line, kind, " ".join(match.group(0).split())))
    return sorted(found)


def _j(*parts: str) -> str:
    """Join the halves of an example (so that this file's source does not match the patterns)."""
    return "".join(parts)


MUST_MATCH = [
    _j("measured at stop", " 26"),
    _j("the Stop", "-26 grid"),
    _j("stops", " 21-23"),
    _j("before issue", " 9"),
    _j("see issue", " #9"),
    _j("Issue", " 11 §5: a Full run"),
    _j("in round", " 3"),
    _j("stop", "\n26 (a wrapped line)"),
    _j("time make demo OUT=/tm", "p/s26/demo"),
    _j("(`git clone . /tm", "p/fresh`)"),
    _j("/wor", "k/main/.venv/bin/pip"),
    _j("/roo", "t/.cache/torch"),
    _j("/hom", "e/alice/data"),
    _j("/User", "s/bob/scenes"),
]

MUST_NOT_MATCH = [
    "stop after the current iteration",
    "Ctrl-C stops the training; a second Ctrl-C stops at once",
    "L_n stops at iteration 3550",
    "--dense-stop 3500",
    "def test_x(tmp_path): scene = tmp_path / 'scene'",
    "pytest's tmp dirs are removed after the run",
    "composited with background 0 and no clamp",
    "around 3 s a run",
    "a known PolGS problem (github.com/owner/repo/issues/3)",
    "runs/work/a, out/tmp/x, data/home/alice",
    "~/tmp/x is the user's own",
    "a round trip through the reader",
]


@pytest.mark.parametrize("text", MUST_MATCH)
def test_patterns_flag_history_and_machine_paths(text: str) -> None:
    assert _hits(text), f"not flagged: {text!r}"


@pytest.mark.parametrize("text", MUST_NOT_MATCH)
def test_patterns_leave_ordinary_text_alone(text: str) -> None:
    assert not _hits(text), f"flagged: {text!r}: {_hits(text)}"


def test_line_numbers_name_the_line_of_the_match() -> None:
    text = _j("first line\nsecond, stop", " 7\nthird")
    assert _hits(text) == [(2, "development round", _j("stop", " 7"))]


def test_the_scan_reaches_every_scanned_place() -> None:
    files = {p.relative_to(ROOT).parts[0] for p in _scanned_files()}
    present = {entry for entry in SCANNED if (ROOT / entry).exists()}
    assert files == present
    assert Path(__file__).resolve() in {p.resolve() for p in _scanned_files()}


def test_user_facing_text_has_no_history_or_machine_paths() -> None:
    problems = []
    for path in _scanned_files():
        text = path.read_text(encoding="utf-8", errors="replace")
        for line, kind, match in _hits(text):
            problems.append(f"{path.relative_to(ROOT)}:{line}: {kind}: {match!r}")
    assert not problems, "history or machine paths in user-facing text:\n" + "\n".join(problems)
