"""YAML loading that remembers where every key and value came from.

PyYAML's composer gives each node a start mark; we walk the node graph once, build plain Python
data (dicts, lists, scalars) and keep a side table ``path -> (line, col)`` so that later validation
errors (pydantic's ``loc`` tuples, semantic checks) can name the exact line of the offending item.
Duplicate keys, which PyYAML silently overwrites, are reported as errors here.
"""

from __future__ import annotations

import math
import os
import re
import stat
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from btmission import limits
from btmission.diagnostics import Diagnostic, Location, Severity, SpecError
from btmission.errors import BtmissionError

PathKey = tuple[str | int, ...]


def format_path(path: Sequence[str | int]) -> str:
    """``('actions', 'takeoff', 'pre', 1)`` → ``actions.takeoff.pre[1]``."""
    out = ""
    for p in path:
        if isinstance(p, int):
            out += f"[{p}]"
        else:
            out += ("." if out else "") + str(p)
    return out


@dataclass
class Source:
    """A loaded YAML document: its data and the positions of every item in it."""

    file: str
    data: Any
    positions: dict[PathKey, tuple[int, int]] = field(default_factory=dict)
    """Where each value starts."""
    key_positions: dict[PathKey, tuple[int, int]] = field(default_factory=dict)
    """Where each mapping key starts (for 'unknown key' and 'missing key' messages)."""

    def locate(self, path: Sequence[str | int], *, key: bool = False) -> Location:
        """Position of ``path``'s value (or its key), else of its nearest existing ancestor."""
        p = tuple(path)
        while p:
            table = self.key_positions if key and p in self.key_positions else self.positions
            if p in table:
                line, col = table[p]
                return Location(self.file, line, col)
            p = p[:-1]
            key = True  # a missing item: point at the key of the nearest ancestor that exists
        line, col = self.positions.get((), (1, 1))
        return Location(self.file, line, col)

    def diag(
        self,
        path: Sequence[str | int],
        message: str,
        code: str,
        severity: Severity = Severity.ERROR,
        *,
        key: bool = False,
    ) -> Diagnostic:
        """A diagnostic located at ``path`` (its value, or its key) in this document."""
        return Diagnostic(severity, code, message, format_path(path), self.locate(path, key=key))


def _check_graph(root: yaml.Node, file: str) -> None:
    """Refuse, before anything is built, a node graph that is cyclic (a recursive alias), nested
    deeper than :data:`~btmission.limits.MAX_YAML_DEPTH` or that repeats more than
    :data:`~btmission.limits.MAX_YAML_ALIAS_NODES` items through aliases ("billion laughs").

    The composer keeps an alias as the very node object of its anchor, so an alias-expanded size
    is counted once per distinct node (memoised), in time linear in the file, without expanding."""
    max_depth = limits.MAX_YAML_DEPTH.limit
    budget = limits.MAX_YAML_ALIAS_NODES.limit
    expanded: dict[int, int] = {}  # id(node) -> nodes in its expansion (itself included)
    on_path: set[int] = set()
    distinct = 0

    def fail(node: yaml.Node, message: str, code: str) -> SpecError:
        m = node.start_mark
        return SpecError(
            [
                Diagnostic(
                    Severity.ERROR, code, message, "", Location(file, m.line + 1, m.column + 1)
                )
            ]
        )

    # iterative post-order walk: (node, depth, children not yet pushed?)
    stack: list[tuple[yaml.Node, int, bool]] = [(root, 1, True)]
    while stack:
        node, depth, enter = stack.pop()
        key = id(node)
        if enter:
            if key in expanded:
                continue
            if key in on_path:
                raise fail(
                    node,
                    "recursive alias: this item contains an alias (*name) to itself, "
                    "so it has no end",
                    "yaml-alias",
                )
            if depth > max_depth:
                m = node.start_mark
                raise _too_deep(file, m.line + 1, m.column + 1, depth)
            distinct += 1
            kids = _children(node)
            if not kids:
                expanded[key] = 1
                continue
            on_path.add(key)
            stack.append((node, depth, False))
            stack.extend((k, depth + 1, True) for k in kids)
            continue
        on_path.discard(key)
        total = 1 + sum(expanded[id(k)] for k in _children(node))
        expanded[key] = total
        if total - distinct > budget:
            raise fail(
                node,
                limits.MAX_YAML_ALIAS_NODES.exceeded(
                    "alias expansion (items repeated through *aliases)", total - distinct
                ),
                "yaml-aliases",
            )


def _children(node: yaml.Node) -> list[yaml.Node]:
    if isinstance(node, yaml.MappingNode):
        return [n for pair in node.value for n in pair]
    if isinstance(node, yaml.SequenceNode):
        return list(node.value)
    return []


def _convert(
    node: yaml.Node,
    path: PathKey,
    src: Source,
    problems: list[Diagnostic],
    loader: yaml.SafeLoader,
) -> Any:
    """Plain data from a checked node graph (:func:`_check_graph` bounds its depth and size)."""
    mark = node.start_mark
    src.positions.setdefault(path, (mark.line + 1, mark.column + 1))
    if isinstance(node, yaml.MappingNode):
        out: dict[Any, Any] = {}
        for key_node, value_node in node.value:
            if not isinstance(key_node, yaml.ScalarNode):
                problems.append(src.diag(path, "mapping keys must be plain names", "yaml-key"))
                continue
            key = str(loader.construct_scalar(key_node))
            kpath = (*path, key)
            kmark = key_node.start_mark
            if key in out:
                first = src.key_positions.get(kpath, (0, 0))[0]
                problems.append(
                    Diagnostic(
                        Severity.ERROR,
                        "duplicate-key",
                        f"duplicate key '{key}' (first defined on line {first})",
                        format_path(kpath),
                        Location(src.file, kmark.line + 1, kmark.column + 1),
                    )
                )
                continue
            src.key_positions[kpath] = (kmark.line + 1, kmark.column + 1)
            out[key] = _convert(value_node, kpath, src, problems, loader)
        return out
    if isinstance(node, yaml.SequenceNode):
        return [_convert(v, (*path, i), src, problems, loader) for i, v in enumerate(node.value)]
    try:
        return loader.construct_object(node, deep=True)
    except yaml.constructor.ConstructorError as exc:  # a tag: !foo, !!python/...
        message = f"cannot read this value: {exc.problem}"
    except ValueError as exc:  # an integer over Python's 4,300-digit limit
        message = f"cannot read this value: {str(exc).split(';')[0].lower()}"
    problems.append(
        Diagnostic(Severity.ERROR, "yaml-value", message, format_path(path),
                   Location(src.file, mark.line + 1, mark.column + 1))
    )  # fmt: skip
    return None


def _too_deep(file: str, line: int = 1, col: int = 1, depth: int | None = None) -> SpecError:
    budget = limits.MAX_YAML_DEPTH
    what = f"is {depth:,}" if depth is not None else "is too deep for the YAML reader"
    return SpecError(
        [Diagnostic(Severity.ERROR, "yaml-depth", f"nesting depth {what}, the limit is "
                    f"{budget.show()} levels (set {budget.env} to change it)", "",
                    Location(file, line, col))]
    )  # fmt: skip


# quoted strings and comments (skipped), flow brackets (counted)
_FLOW_TOKEN = re.compile(
    r""""(?:[^"\\]|\\.)*"|'(?:[^']|'')*'|(?:^|(?<=\s))#[^\n]*|[\[\]{}]""", re.M
)


def _check_flow_depth(text: str, file: str) -> None:
    """Refuse ``[[[[...`` / ``{{{...`` nested deeper than the budget before PyYAML sees it (its
    scanner slows down quadratically with flow depth, its composer recurses)."""
    if text.count("[") + text.count("{") <= (limit := limits.MAX_YAML_DEPTH.limit):
        return
    depth = 0
    for m in _FLOW_TOKEN.finditer(text):
        c = m.group()
        if c in "[{":
            depth += 1
            if depth > limit:
                line = text.count("\n", 0, m.start()) + 1
                col = m.start() - (text.rfind("\n", 0, m.start()) + 1) + 1
                raise _too_deep(file, line, col, depth)
        elif c in "]}":
            depth = max(0, depth - 1)


# YAML 1.1 (PyYAML) reads ``1e5`` and ``2.5e-3`` as strings (it wants ``1.0e+5``); users of a
# robotics tool write them as numbers, as YAML 1.2 does. Both loaders resolve them as floats.
_EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")


class _SafeLoader(yaml.SafeLoader):
    """PyYAML's safe loader, reading ``1e5`` as a number."""


_SafeLoader.add_implicit_resolver("tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789."))


def _construct_float(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> float | str:
    """A float; a literal too large for one (``1e400``) stays text, so that the check that
    refuses it quotes what the user wrote rather than ``inf``."""
    value = yaml.SafeLoader.construct_yaml_float(loader, node)
    text = str(node.value)
    return text if math.isinf(value) and "inf" not in text.lower() else value


_SafeLoader.add_constructor("tag:yaml.org,2002:float", _construct_float)

_FAST_LOADER: Any = None
if hasattr(yaml, "CSafeLoader"):  # libyaml's, when PyYAML was built with it

    class _FastLoader(yaml.CSafeLoader):  # type: ignore[misc, name-defined]
        """libyaml's safe loader, reading ``1e5`` as a number."""

    _FastLoader.add_implicit_resolver(
        "tag:yaml.org,2002:float", _EXPONENT_FLOAT, list("-+0123456789.")
    )
    _FAST_LOADER = _FastLoader


def _compose(text: str) -> yaml.Node | None:
    """The node graph of ``text``: by libyaml when available (several times faster on large
    files), else, and whenever libyaml finds an error, by PyYAML itself, whose messages (and
    positions) are the ones btmission documents."""
    if _FAST_LOADER is not None:
        try:
            return yaml.compose(text, Loader=_FAST_LOADER)  # type: ignore[no-any-return]
        except yaml.YAMLError:
            pass  # PyYAML says what is wrong
    return yaml.compose(text, Loader=_SafeLoader)  # type: ignore[no-any-return]


def parse_yaml(text: str, file: str = "<input>") -> Source:
    """Parse one YAML document, keeping positions. Raises :class:`SpecError` on bad YAML."""
    _check_flow_depth(text, file)
    try:
        node = _compose(text)
    except RecursionError:  # PyYAML's composer recurses once per nesting level
        raise _too_deep(file) from None
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        what = " ".join(str(x) for x in (exc.context, exc.problem) if x)
        if exc.context_mark is not None and "end of stream" in str(exc.problem):
            mark = exc.context_mark  # e.g. an unterminated quote: point where it starts
        where = Location(file, mark.line + 1, mark.column + 1) if mark else Location(file)
        raise SpecError(
            [Diagnostic(Severity.ERROR, "yaml-syntax", f"YAML syntax error: {what}", "", where)]
        ) from None
    except yaml.YAMLError as exc:  # pragma: no cover - non-marked errors are rare
        raise SpecError(
            [Diagnostic(Severity.ERROR, "yaml-syntax", f"YAML error: {exc}", "", Location(file))]
        ) from None
    src = Source(file=file, data=None)
    if node is None:
        raise SpecError(
            [Diagnostic(Severity.ERROR, "empty", "the file is empty", "", Location(file, 1, 1))]
        )
    _check_graph(node, file)
    problems: list[Diagnostic] = []
    try:
        src.data = _convert(node, (), src, problems, _SafeLoader(""))
    except RecursionError:  # only when BTMISSION_MAX_YAML_DEPTH was raised very high
        raise _too_deep(file) from None
    if problems:
        raise SpecError(problems)
    return src


def read_yaml(path: str | Path) -> Source:
    """Read and parse a YAML file; unreadable files become a :class:`SpecError`.

    Only regular files are read (a FIFO, ``/dev/zero`` or a directory is refused without waiting
    on it), and only up to :data:`~btmission.limits.MAX_FILE_BYTES`."""
    p = Path(path)

    def refuse(code: str, message: str) -> SpecError:
        return SpecError([Diagnostic(Severity.ERROR, code, message, "", Location(str(p)))])

    try:
        data = read_regular_file(p, limits.MAX_FILE_BYTES)
        text = data.decode("utf-8")
    except FileNotFoundError:
        raise refuse("no-file", "file not found") from None
    except FileRefused as exc:
        raise refuse(exc.code, str(exc)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise refuse("unreadable", f"cannot read: {exc}") from None
    return parse_yaml(text, str(p))


class FileRefused(BtmissionError, OSError):
    """A file that is not read: larger than its budget (``code`` ``too-large``) or not a regular
    file (``unreadable``)."""

    def __init__(self, message: str, code: str) -> None:
        super().__init__(message)
        self.code = code


_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def read_regular_file(path: Path, budget: limits.Budget) -> bytes:
    """The bytes of ``path`` when it is a regular file of at most ``budget`` bytes.

    Raises :class:`FileRefused` (an :class:`OSError`) naming the problem otherwise. The file is
    opened non-blocking and checked again once open, so a FIFO swapped in never blocks the read."""
    limit = budget.limit
    fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a file")
            raise FileRefused(
                f"not a regular file but {kind}: only regular files are read", "unreadable"
            )
        if st.st_size > limit:
            raise FileRefused(_too_large(st.st_size, budget), "too-large")
        with os.fdopen(fd, "rb", closefd=False) as fh:
            # read what stat said (+1: did it grow?), not limit + 1: read(n) allocates n bytes
            data = fh.read(min(limit, st.st_size) + 1)
            while len(data) <= limit and (more := fh.read(min(1 << 20, limit + 1 - len(data)))):
                data += more
    finally:
        os.close(fd)
    if len(data) > limit:  # grew while we read it
        raise FileRefused(_too_large(len(data), budget), "too-large")
    return data


def _too_large(size: int, budget: limits.Budget) -> str:
    return (
        f"file too large: {size:,} bytes, the limit is {budget.show()} bytes "
        f"(set {budget.env} to change it)"
    )
