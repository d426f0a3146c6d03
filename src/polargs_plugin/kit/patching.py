"""Anchor-line patching: insert marked lines into a user's checkout of an upstream trainer.

The patch scripts ``adapters/<name>/patch.py`` each hold one trainer's list of :class:`Anchor`
and hand it to :func:`main`; everything else lives here and knows nothing about any trainer.

How a file is patched:

1. Every line ending with :data:`MARKER` is dropped first, so the engine always works on the
   un-patched text ("base"). Patching a patched file therefore reproduces the same file (no
   change), and an older patch is replaced rather than stacked.
2. The base is split into *logical lines* (one Python statement each, continuation lines joined
   with single spaces, comments cut off; comment-only lines are never candidates) with
   :mod:`tokenize`.
3. The anchors are located in list order. Each anchor's regex may use ``{name}`` placeholders for
   values captured by earlier anchors (inserted with :func:`re.escape`); its named groups add to a
   single dict of captured names shared by all anchors (a name captured twice must agree). Scope
   fields (``after``, ``before``, ``inside``, ``same_indent_as``) restrict the candidates using
   anchors found earlier. An anchor must match exactly once (``pick='only'``), or the first or
   last candidate is taken (``pick='first'`` / ``'last'``). An anchor with ``refuse`` set is a
   shape the script knows it cannot handle: if it matches, nothing is written and the reason is
   the error.
4. Each anchor's template lines are filled from the shared dict (so a line inserted before the
   training loop can use names captured from the render call further down), indented like the
   anchor line, suffixed with ``  # polargs-patch`` and inserted before its first physical line or
   after its last one.
5. The result must still compile (when the base did), and every name an inserted line reads must
   be bound where that line runs (:func:`unbound_reads`): a keyword copied from the render call
   inside the loop to a line above it would otherwise fail at run time. Then it is written
   atomically (temporary file in the same folder + :func:`os.replace`), keeping the file mode,
   after the base has been saved as ``<file>.polargs-orig``. A read-only file is refused unless
   ``--force``.

Only the standard library is imported (here and in :mod:`.inria_anchors`), so that a patch script
runs with any Python 3.8+ before the trainer's environment is complete
(``adapters/patch_engine.py`` loads these two modules without importing the package).

Errors that mean "this is not the loop we know" (an anchor missing or ambiguous, inconsistent
captures) leave every file untouched, print one line
``error: <file>: anchor '<name>' not found (<what it looks for>)`` (or ``matches N lines``)
and give exit status 2.
"""

from __future__ import annotations

import argparse
import ast
import builtins
import difflib
import io
import os
import re
import stat
import sys
import tempfile
import tokenize
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

MARKER = "# polargs-patch"
"""Comment that ends every inserted line; lines ending with it are what ``--revert`` and re-patching drop."""

BACKUP_SUFFIX = ".polargs-orig"
"""Suffix of the backup written next to the patched file (``train.py.polargs-orig``)."""

EXIT_OK = 0
EXIT_UNRECOGNISED = 2

_PLACEHOLDER = re.compile(r"\{([A-Za-z_]\w*)\}")


@dataclass(frozen=True)
class Anchor:
    """One anchor: a statement to find in the file, and the lines to insert next to it."""

    name: str
    """Short human name, used in error messages (``anchor 'loss backward' not found``)."""

    regex: str
    """Pattern matched (:func:`re.match`) against the logical line, indentation included.
    Named groups ``(?P<x>...)`` are captured into the shared dict; ``{x}`` placeholders are replaced
    by the escaped value earlier anchors captured for ``x``."""

    where: str = "before"
    """``'before'``: insert above the statement's first line; ``'after'``: below its last line."""

    lines: tuple[str, ...] = ()
    """Template lines to insert, :meth:`str.format` style over the shared dict of captured names
    (``"{loss} = {loss} + polar.loss({iteration}, {camera}, {render_pkg})"``). Written without
    indentation or marker; both are added. Empty for anchors that only locate or capture."""

    looks_for: str = ""
    """What the anchor looks for, in words, for the error message
    (``"the `loss.backward()` call inside the training loop"``)."""

    pick: str = "only"
    """``'only'``: exactly one candidate must match; ``'first'`` / ``'last'``: take the first /
    last of several (the last top-level import; the first ``no_grad`` block after the backward)."""

    after: str | None = None
    """Name of an earlier anchor: only statements below it are candidates."""

    before: str | None = None
    """Name of an earlier anchor: only statements above it are candidates."""

    inside: str | None = None
    """Name of an earlier anchor that opens a block (``for``, ``with``, ``if``): only statements
    inside that block are candidates."""

    same_indent_as: str | None = None
    """Name of an earlier anchor: only statements indented exactly like it are candidates."""

    defaults: Mapping[str, str] = field(default_factory=dict)
    """Values for named groups that did not take part in the match (optional groups)."""

    refuse: str = ""
    """Non-empty: the anchor describes a shape the script refuses, and this is why (one line). A
    match stops the patch with ``error: <file>: <refuse> (L<n>)``; no match is not an error."""

    def __post_init__(self) -> None:
        if self.where not in ("before", "after"):
            raise ValueError(f"anchor {self.name!r}: where must be 'before' or 'after', not {self.where!r}")
        if self.pick not in ("only", "first", "last"):
            raise ValueError(f"anchor {self.name!r}: pick must be 'only', 'first' or 'last', not {self.pick!r}")
        if self.refuse and self.lines:
            raise ValueError(f"anchor {self.name!r}: a refusing anchor inserts nothing")
        for line in self.lines:
            if "\n" in line or "\r" in line or MARKER in line:
                raise ValueError(f"anchor {self.name!r}: template lines are single lines without the marker")


@dataclass(frozen=True)
class LogicalLine:
    """One Python statement of the file as the anchors see it."""

    first: int
    """Index (0-based) of its first physical line."""

    last: int
    """Index (0-based) of its last physical line (== ``first`` for a one-line statement)."""

    text: str
    """The statement on one line: leading indentation kept, continuation lines stripped and joined
    with single spaces, comments and the line ending removed."""

    indent: str
    """Leading whitespace of its first physical line (what inserted lines are indented with)."""


@dataclass(frozen=True)
class Found:
    """Where one anchor matched."""

    anchor: Anchor
    """The anchor."""

    line: LogicalLine
    """The statement it matched."""


class PatchError(Exception):
    """A file cannot be patched or reverted; ``str(err)`` is the one-line message (no ``error:``)."""

    def __init__(self, message: str, status: int = EXIT_UNRECOGNISED) -> None:
        super().__init__(message)
        self.status = status
        """Exit status :func:`main` returns for it."""


# ----------------------------------------------------------------------------------------------
# text helpers


def decode(data: bytes) -> str:
    """Bytes -> text, losslessly (UTF-8; undecodable bytes survive as surrogates)."""
    return data.decode("utf-8", errors="surrogateescape")


def encode(text: str) -> bytes:
    """Inverse of :func:`decode`."""
    return text.encode("utf-8", errors="surrogateescape")


def is_marked(line: str) -> bool:
    """Whether a physical line (line ending allowed) was inserted by a patch."""
    return line.rstrip("\r\n").rstrip().endswith(MARKER)


def strip_marked(text: str) -> str:
    """``text`` without its marked lines: the un-patched base of a (possibly) patched file."""
    return "".join(line for line in text.splitlines(keepends=True) if not is_marked(line))


def _indent_width(indent: str) -> int:
    return len(indent.expandtabs(8))


def _line_ending(line: str) -> str:
    if line.endswith("\r\n"):
        return "\r\n"
    if line.endswith(("\n", "\r")):
        return line[-1]
    return ""


# ----------------------------------------------------------------------------------------------
# logical lines


def logical_lines(lines: Sequence[str]) -> list[LogicalLine]:
    """Split physical lines (with endings) into statements; falls back to one per line on bad syntax."""
    try:
        return _logical_lines_tokenize(lines)
    except (tokenize.TokenError, IndentationError, SyntaxError):
        return _logical_lines_physical(lines)


def _logical_lines_tokenize(lines: Sequence[str]) -> list[LogicalLine]:
    readline = io.StringIO("".join(lines)).readline
    comments: dict[int, int] = {}
    spans: list[tuple[int, int]] = []
    start: int | None = None
    skip = (tokenize.NL, tokenize.COMMENT, tokenize.INDENT, tokenize.DEDENT, tokenize.ENCODING)
    for tok in tokenize.generate_tokens(readline):
        if tok.type == tokenize.COMMENT:
            comments[tok.start[0] - 1] = tok.start[1]
        if tok.type in (tokenize.NEWLINE, tokenize.ENDMARKER):
            if start is not None:
                spans.append((start, tok.start[0] - 1))
            start = None
        elif tok.type not in skip and start is None:
            start = tok.start[0] - 1
    return [_make_logical(lines, first, min(last, len(lines) - 1), comments) for first, last in spans]


def _make_logical(lines: Sequence[str], first: int, last: int, comments: Mapping[int, int]) -> LogicalLine:
    parts = []
    for i in range(first, last + 1):
        raw = lines[i].rstrip("\r\n")
        if i in comments:
            raw = raw[: comments[i]]
        parts.append(raw.rstrip() if i == first else raw.strip())
    text = " ".join(p for p in parts if p)
    first_line = lines[first]
    indent = first_line[: len(first_line) - len(first_line.lstrip(" \t"))]
    return LogicalLine(first=first, last=last, text=text, indent=indent)


def _logical_lines_physical(lines: Sequence[str]) -> list[LogicalLine]:
    out = []
    for i, line in enumerate(lines):
        stripped = line.strip()
        if stripped and not stripped.startswith("#"):
            out.append(_make_logical(lines, i, i, {}))
    return out


def block_last_line(statements: Sequence[LogicalLine], opener: LogicalLine) -> int:
    """Index of the last physical line of the block that ``opener`` (``for``/``with``/``if`` ...) opens."""
    width = _indent_width(opener.indent)
    last = opener.last
    for stmt in statements:
        if stmt.first <= opener.last:
            continue
        if _indent_width(stmt.indent) <= width:
            break
        last = stmt.last
    return last


# ----------------------------------------------------------------------------------------------
# locating anchors


def expand_regex(anchor: Anchor, captured: Mapping[str, str]) -> str:
    """The anchor's regex with its ``{name}`` placeholders replaced by escaped captured values."""

    def substitute(match: re.Match[str]) -> str:
        key = match.group(1)
        if key not in captured:
            raise PatchError(f"anchor '{anchor.name}' uses {{{key}}}, which no earlier anchor captured")
        return re.escape(captured[key])

    return _PLACEHOLDER.sub(substitute, anchor.regex)


def _in_scope(stmt: LogicalLine, anchor: Anchor, found: Mapping[str, Found], statements: Sequence[LogicalLine]) -> bool:
    if anchor.after is not None and stmt.first <= found[anchor.after].line.last:
        return False
    if anchor.before is not None and stmt.last >= found[anchor.before].line.first:
        return False
    if anchor.inside is not None:
        opener = found[anchor.inside].line
        if not opener.last < stmt.first <= block_last_line(statements, opener):
            return False
    if anchor.same_indent_as is not None and stmt.indent != found[anchor.same_indent_as].line.indent:
        return False
    return True


def _check_references(anchors: Sequence[Anchor]) -> None:
    seen: set[str] = set()
    locating: set[str] = set()  # refusing anchors locate nothing, so nothing can refer to them
    for anchor in anchors:
        for ref in (anchor.after, anchor.before, anchor.inside, anchor.same_indent_as):
            if ref is not None and ref not in locating:
                why = "a refusing anchor, which locates nothing" if ref in seen else "not an earlier anchor"
                raise ValueError(f"anchor {anchor.name!r} refers to {ref!r}, which is {why}")
        if anchor.name in seen:
            raise ValueError(f"two anchors are named {anchor.name!r}")
        seen.add(anchor.name)
        if not anchor.refuse:
            locating.add(anchor.name)


def _describe(anchor: Anchor) -> str:
    return f" ({anchor.looks_for})" if anchor.looks_for else ""


def locate(
    anchors: Sequence[Anchor], statements: Sequence[LogicalLine], filename: str
) -> tuple[dict[str, Found], dict[str, str]]:
    """Find every anchor; returns where each matched and the shared dict of captured names."""
    _check_references(anchors)
    found: dict[str, Found] = {}
    captured: dict[str, str] = {}
    for anchor in anchors:
        pattern = re.compile(expand_regex(anchor, captured))
        hits = [(s, m) for s in statements if _in_scope(s, anchor, found, statements) and (m := pattern.match(s.text))]
        if anchor.refuse:
            if hits:
                raise PatchError(f"{filename}: {anchor.refuse} (L{hits[0][0].first + 1})")
            continue
        if not hits:
            raise PatchError(f"{filename}: anchor '{anchor.name}' not found{_describe(anchor)}")
        if len(hits) > 1 and anchor.pick == "only":
            where = ", ".join(f"L{s.first + 1}" for s, _ in hits)
            raise PatchError(
                f"{filename}: anchor '{anchor.name}' matches {len(hits)} lines ({where}){_describe(anchor)}"
            )
        stmt, match = hits[0] if anchor.pick == "first" else hits[-1]
        _merge_captures(anchor, match, captured, filename)
        found[anchor.name] = Found(anchor=anchor, line=stmt)
    return found, captured


def _merge_captures(anchor: Anchor, match: re.Match[str], captured: dict[str, str], filename: str) -> None:
    for key, value in match.groupdict().items():
        if value is None:
            value = anchor.defaults.get(key)
        if value is None:
            continue
        if key in captured and captured[key] != value:
            raise PatchError(
                f"{filename}: anchor '{anchor.name}' captured {key}='{value}'"
                f" but an earlier anchor captured '{captured[key]}'"
            )
        captured[key] = value


# ----------------------------------------------------------------------------------------------
# applying


def fill(anchor: Anchor, captured: Mapping[str, str], filename: str) -> list[str]:
    """The anchor's template lines with the captured names filled in (no indent, no marker)."""
    try:
        return [template.format_map(captured) for template in anchor.lines]
    except KeyError as err:
        raise PatchError(f"{filename}: anchor '{anchor.name}': no anchor captured {err.args[0]!r}") from None


def _insertions(
    found: Mapping[str, Found], captured: Mapping[str, str], lines: Sequence[str], filename: str
) -> dict[int, list[str]]:
    """Physical index -> marked lines to insert before it (``len(lines)`` for the end of file)."""
    out: dict[int, list[str]] = {}
    for item in found.values():
        if not item.anchor.lines:
            continue
        stmt = item.line
        index = stmt.first if item.anchor.where == "before" else stmt.last + 1
        ending = _line_ending(lines[stmt.last]) or _line_ending(lines[0]) or "\n"
        new = [f"{stmt.indent}{text}  {MARKER}{ending}" for text in fill(item.anchor, captured, filename)]
        out.setdefault(index, []).extend(new)
    return out


def apply_anchors(base: str, anchors: Sequence[Anchor], filename: str = "<file>") -> str:
    """Patch an un-patched text: locate all anchors, then insert all template lines."""
    lines = base.splitlines(keepends=True)
    found, captured = locate(anchors, logical_lines(lines), filename)
    inserts = _insertions(found, captured, lines, filename)
    if inserts.get(len(lines)) and not _line_ending(lines[-1]):
        lines[-1] += _line_ending(lines[0]) or "\n"  # something goes after a last line without ending
    out: list[str] = []
    for index in range(len(lines) + 1):
        out.extend(inserts.get(index, []))
        if index < len(lines):
            out.append(lines[index])
    return "".join(out)


def _compiles(text: str, filename: str) -> str | None:
    try:
        compile(text, filename, "exec", dont_inherit=True)
    except (SyntaxError, ValueError) as err:
        return str(err)
    return None


def patched_text(current: str, anchors: Sequence[Anchor], filename: str) -> str:
    """What the file should read once patched, from its current (possibly patched) text."""
    base = strip_marked(current)
    new = apply_anchors(base, anchors, filename)
    if _compiles(base, filename) is not None:
        return new  # not Python we can parse: the anchors alone decide
    if (problem := _compiles(new, filename)) is not None:
        raise PatchError(f"{filename}: the patched file would not compile ({problem}); nothing written")
    inserted = [i + 1 for i, line in enumerate(new.splitlines()) if is_marked(line)]

    def base_line(line: int) -> int:  # a line of the patched text -> the un-patched file's line
        return line - sum(1 for marked in inserted if marked < line)

    for line, name, bound_at in unbound_reads(new, inserted):
        where = f"first bound at L{base_line(bound_at)}, below it" if bound_at else "not bound in its scope"
        raise PatchError(
            f"{filename}: the line to insert above L{base_line(line)} would read '{name}' before it is bound"
            f" ({where}); nothing written"
        )
    return new


# ----------------------------------------------------------------------------------------------
# names an inserted line reads


_SCOPES = (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)
_COMPREHENSIONS = (ast.ListComp, ast.SetComp, ast.DictComp, ast.GeneratorExp)


def _local_nodes(node: ast.AST) -> list[ast.AST]:
    """The nodes of ``node``'s own scope: nested functions, classes, lambdas and comprehensions are
    not entered (their names, and the defaults and decorators of a def, belong to ``node``'s scope)."""
    out: list[ast.AST] = []
    stack = list(ast.iter_child_nodes(node))
    while stack:
        child = stack.pop()
        out.append(child)
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
            stack.extend([*child.decorator_list, *child.args.defaults, *child.args.kw_defaults])
        elif isinstance(child, ast.ClassDef):
            stack.extend([*child.decorator_list, *child.bases])
        elif not isinstance(child, (ast.Lambda, *_COMPREHENSIONS)):
            stack.extend(ast.iter_child_nodes(child))
    return [n for n in out if n is not None]


def _bindings(scope: ast.AST) -> dict[str, int]:
    """Name -> first line where ``scope`` binds it (parameters: the ``def`` line)."""
    first: dict[str, int] = {}

    def bind(name: str, line: int) -> None:
        if name not in first or line < first[name]:
            first[name] = line

    if isinstance(scope, (ast.FunctionDef, ast.AsyncFunctionDef)):
        args = scope.args
        for arg in [*getattr(args, "posonlyargs", []), *args.args, *args.kwonlyargs, args.vararg, args.kwarg]:
            if arg is not None:
                bind(arg.arg, scope.lineno)
    for node in _local_nodes(scope):
        if isinstance(node, ast.Name) and isinstance(node.ctx, (ast.Store, ast.Del)):
            bind(node.id, node.lineno)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            for alias in node.names:
                bind(alias.asname or alias.name.split(".")[0], node.lineno)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bind(node.name, node.lineno)
        elif isinstance(node, ast.ExceptHandler) and node.name:
            bind(node.name, node.lineno)
        elif isinstance(node, (ast.Global, ast.Nonlocal)):
            for name in node.names:
                bind(name, 0)  # bound elsewhere: not this check's business
    return first


def _scopes_of_lines(tree: ast.Module, lines: set[int]) -> dict[int, tuple[ast.stmt, list[ast.AST]]]:
    """Line -> (the statement starting there, its enclosing scopes from the module inwards)."""
    found: dict[int, tuple[ast.stmt, list[ast.AST]]] = {}
    stack: list[tuple[ast.AST, list[ast.AST]]] = [(tree, [tree])]
    while stack:
        node, scopes = stack.pop()
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.stmt) and child.lineno in lines and child.lineno not in found:
                found[child.lineno] = (child, scopes)
            if isinstance(child, _SCOPES):
                stack.append((child, [*scopes, child]))
            else:
                stack.append((child, scopes))
    return found


def _reads(statement: ast.stmt) -> list[tuple[str, int]]:
    """(name, line) of the names a statement loads, outside the comprehensions and lambdas in it."""
    return [
        (node.id, node.lineno)
        for node in [statement, *_local_nodes(statement)]
        if isinstance(node, ast.Name) and isinstance(node.ctx, ast.Load)
    ]


def unbound_reads(text: str, lines: Sequence[int]) -> list[tuple[int, str, int]]:
    """Names that the statements starting on ``lines`` (1-based) read before their scope binds them.

    A name counts as bound for a statement when its own function binds it on an earlier line
    (parameters included), an enclosing function or the module binds it anywhere (they have run
    by the time the function is called; at module level: on an earlier line), or it is a builtin.
    Conditional bindings count as bindings: the check catches names that are assigned only
    further down (inside the training loop, say), not every possible NameError.

    Returns:
        ``(line, name, line of its first binding in that scope or 0)`` per unbound read.
    """
    tree = ast.parse(text)
    builtin_names = set(dir(builtins))
    scope_bindings: dict[int, dict[str, int]] = {}
    problems = []
    for line, (statement, scopes) in sorted(_scopes_of_lines(tree, set(lines)).items()):
        own = scopes[-1]
        for scope in scopes:
            scope_bindings.setdefault(id(scope), _bindings(scope))
        outer = set().union(*(scope_bindings[id(s)] for s in scopes[:-1])) if len(scopes) > 1 else set()
        mine = scope_bindings[id(own)]
        for name, _ in _reads(statement):
            if name in builtin_names or name in outer or (name in mine and mine[name] < line):
                continue
            problems.append((line, name, mine.get(name, 0)))
    return problems


# ----------------------------------------------------------------------------------------------
# files


def backup_path(path: Path) -> Path:
    """``train.py`` -> ``train.py.polargs-orig`` next to it."""
    return path.with_name(path.name + BACKUP_SUFFIX)


def write_atomic(path: Path, data: bytes, mode: int | None = None) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and :func:`os.replace`.

    ``mode`` (permission bits) defaults to the existing file's, else to the umask default."""
    if mode is None and path.exists():
        mode = path.stat().st_mode & 0o7777
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            os.fsync(handle.fileno())
        if mode is not None:
            os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def unified_diff(old: str, new: str, path: Path) -> str:
    """Unified diff between two versions of ``path`` (empty when they are equal)."""
    return "".join(
        difflib.unified_diff(
            old.splitlines(keepends=True),
            new.splitlines(keepends=True),
            fromfile=f"{path} (current)",
            tofile=f"{path} (new)",
        )
    )


def resolve_target(target: str | os.PathLike[str], filename: str = "train.py", subfolders: Sequence[str] = ()) -> Path:
    """A checkout folder -> its ``filename``, found in the folder or in one of its ``subfolders``
    (gsplat's trainer lives in ``examples/`` of the repository); a file is taken as is."""
    path = Path(target)
    if not path.is_dir():
        if not path.is_file():
            raise PatchError(f"{path}: no such file or folder")
        return path
    for folder in (path, *(path / sub for sub in subfolders)):
        if (folder / filename).is_file():
            return folder / filename
    places = " or ".join([f"{path}", *(f"{path / sub}{os.sep}" for sub in subfolders)])
    raise PatchError(f"{path}: no {filename} in {places}; pass the trainer's checkout or the file itself")


def is_read_only(path: Path) -> bool:
    """Whether ``path`` is read-only: no write permission bit at all, or not writable by us.

    The bits are looked at too because the superuser may write to any file: a mode of 0444
    still says the owner wants the file left alone."""
    return not path.stat().st_mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH) or not os.access(path, os.W_OK)


def _refuse_read_only(path: Path, force: bool, action: str) -> None:
    if is_read_only(path) and not force:
        mode = stat.S_IMODE(path.stat().st_mode)
        raise PatchError(f"{path}: read-only (mode {mode:04o}); --force {action} it anyway, keeping the mode")


def patch_file(path: Path, anchors: Sequence[Anchor], dry_run: bool = False, force: bool = False) -> str:
    """Patch one file (or, with ``dry_run``, return the diff and write nothing); returns the report.

    The backup always holds the file's current un-patched text: written on the first patch, and
    refreshed when the file changed under it (an upstream update patched again, say). A read-only
    file is refused unless ``force`` (the file is replaced by a rename, which its mode does not
    prevent, so the mode is the only sign that it should stay as it is)."""
    current = decode(path.read_bytes())
    new = patched_text(current, anchors, str(path))
    if dry_run:
        return unified_diff(current, new, path)
    if new != current:
        _refuse_read_only(path, force, "patches")
    mode = path.stat().st_mode & 0o7777
    note = _ensure_backup(path, encode(strip_marked(current)), mode)
    if new == current:
        return f"{path}: already patched, no change{note}"
    write_atomic(path, encode(new), mode)
    added = sum(1 for line in new.splitlines() if is_marked(line))
    return f"{path}: patched, {added} lines inserted; backup {backup_path(path)}{note}"


def _ensure_backup(path: Path, base: bytes, mode: int) -> str:
    """Make ``<file>.polargs-orig`` hold ``base``; returns a note for the report when it was refreshed."""
    backup = backup_path(path)
    if backup.exists() and backup.read_bytes() == base:
        return ""
    existed = backup.exists()
    write_atomic(backup, base, mode)
    return f" (backup {backup.name} refreshed)" if existed else ""


def revert_file(path: Path, dry_run: bool = False, force: bool = False) -> str:
    """Restore the file from its backup (byte-identical) and delete the backup; returns the report.

    Without a backup the marked lines are removed instead. Refuses when the file was edited
    since patching (its un-patched text differs from the backup) or is read-only, unless ``force``."""
    current_bytes = path.read_bytes()
    current = decode(current_bytes)
    backup = backup_path(path)
    if backup.exists():
        original = backup.read_bytes()
        if encode(strip_marked(current)) != original and not force:
            raise PatchError(
                f"{path}: changed since it was patched (differs from {backup.name} beyond the marked lines);"
                " --force restores the backup anyway"
            )
        if dry_run:
            return unified_diff(current, decode(original), path)
        _refuse_read_only(path, force, "reverts")
        write_atomic(path, original, path.stat().st_mode & 0o7777)
        backup.unlink()
        return f"{path}: restored from {backup.name}, backup removed"
    stripped = strip_marked(current)
    if stripped == current:
        return "" if dry_run else f"{path}: not patched (no backup, no marked lines), nothing to revert"
    if dry_run:
        return unified_diff(current, stripped, path)
    _refuse_read_only(path, force, "reverts")
    write_atomic(path, encode(stripped), path.stat().st_mode & 0o7777)
    return f"{path}: no backup found; removed the lines marked '{MARKER}'"


# ----------------------------------------------------------------------------------------------
# command line


def build_parser(description: str, filename: str = "train.py") -> argparse.ArgumentParser:
    """The command line every ``adapters/<name>/patch.py`` shares (``filename``: the file patched
    in a checkout folder by default)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkout", help=f"the trainer's checkout (folder holding {filename}) or the file itself")
    parser.add_argument("--file", default=filename, help=f"file to patch inside the checkout (default: {filename})")
    parser.add_argument("--dry-run", action="store_true", help="print the unified diff, write nothing")
    parser.add_argument(
        "--revert", action="store_true", help=f"restore the file from <file>{BACKUP_SUFFIX} and remove the backup"
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="patch (or revert) a read-only file; with --revert: restore even if the file was edited after patching",
    )
    return parser


def main(argv: Sequence[str] | None, anchors: Sequence[Anchor], description: str = "", filename: str = "train.py",
         subfolders: Sequence[str] = ()) -> int:
    """Entry point of a patch script: parse ``argv``, patch / dry-run / revert, return the exit status
    (``subfolders`` of a checkout folder are searched for the file too, as :func:`resolve_target`)."""
    args = build_parser(description, filename).parse_args(argv)
    try:
        path = resolve_target(args.checkout, args.file, subfolders)
        if path.is_symlink():
            # patch the file the link points to, through a rename beside it: the link stays a link
            link, path = path, path.resolve()
            if not path.is_file():
                raise PatchError(f"{link}: a link to {path}, which is not a file")
            print(f"{link}: a link; acting on its target {path} (the link is kept)", file=sys.stderr)
        if args.revert:
            report = revert_file(path, dry_run=args.dry_run, force=args.force)
        else:
            report = patch_file(path, anchors, dry_run=args.dry_run, force=args.force)
    except PatchError as err:
        print(f"error: {err}", file=sys.stderr)
        return err.status
    except OSError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if report:
        print(report, end="" if report.endswith("\n") else "\n")
    elif args.dry_run:
        print(f"{path}: no change", file=sys.stderr)
    return EXIT_OK
