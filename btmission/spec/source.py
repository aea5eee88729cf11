"""YAML loading that remembers where every key and value came from.

PyYAML's composer gives each node a start mark; we walk the node graph once, build plain Python
data (dicts, lists, scalars) and keep a side table ``path -> (line, col)`` so that later validation
errors (pydantic's ``loc`` tuples, semantic checks) can name the exact line of the offending item.
Duplicate keys, which PyYAML silently overwrites, are reported as errors here.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError

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


def _convert(
    node: yaml.Node,
    path: PathKey,
    src: Source,
    problems: list[Diagnostic],
    loader: yaml.SafeLoader,
) -> Any:
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
    return loader.construct_object(node, deep=True)


def parse_yaml(text: str, file: str = "<input>") -> Source:
    """Parse one YAML document, keeping positions. Raises :class:`SpecError` on bad YAML."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
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
    problems: list[Diagnostic] = []
    src.data = _convert(node, (), src, problems, yaml.SafeLoader(""))
    if problems:
        raise SpecError(problems)
    return src


def read_yaml(path: str | Path) -> Source:
    """Read and parse a YAML file; unreadable files become a :class:`SpecError`."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise SpecError(
            [Diagnostic(Severity.ERROR, "no-file", "file not found", "", Location(str(p)))]
        ) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SpecError(
            [Diagnostic(Severity.ERROR, "unreadable", f"cannot read: {exc}", "", Location(str(p)))]
        ) from None
    return parse_yaml(text, str(p))
