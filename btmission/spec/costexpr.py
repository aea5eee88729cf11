"""Task cost expressions such as ``path_cost(pickup) + path_cost(pickup, dropoff)``.

A task type's ``cost`` is what an agent bids: f_cost(task, state) in seed 003 eq. 8, e.g.
Γ1 = path_cost(location) for inspection (eq. 9) and Γ2 = path_cost(pickup) +
path_cost(pickup, dropoff) for pick-and-deliver (eq. 10). The agent multiplies it by k_bt.

Grammar (a safe subset of Python expressions): numbers, task field names, ``+ - * /``,
parentheses and calls of the cost functions below. ``path_cost(a)`` is the path cost from the
agent's position to ``a``; ``path_cost(a, b)`` from ``a`` to ``b``; ``distance`` is the same with
straight lines.
"""

from __future__ import annotations

import ast
import math
import operator
from collections.abc import Callable, Mapping
from dataclasses import dataclass

from btmission.errors import BtmissionError

COST_FUNCTIONS = {"path_cost": (1, 2), "distance": (1, 2)}
"""Allowed functions and their (min, max) number of arguments."""

_BINOPS: dict[type[ast.operator], Callable[[float, float], float]] = {
    ast.Add: operator.add,
    ast.Sub: operator.sub,
    ast.Mult: operator.mul,
    ast.Div: operator.truediv,
}


_OP_TEXT: dict[type[ast.operator], str] = {
    ast.Pow: "**",
    ast.Mod: "%",
    ast.FloorDiv: "//",
    ast.MatMult: "@",
    ast.BitAnd: "&",
    ast.BitOr: "|",
    ast.BitXor: "^",
    ast.LShift: "<<",
    ast.RShift: ">>",
}


MAX_COST_CHARS = 10_000
"""Longest cost expression read (a real one is a few dozen characters)."""
MAX_COST_DEPTH = 200
"""Deepest operator nesting of a cost expression (``1+1+...`` nests once per ``+``); evaluation
recurses once per level."""


def _short(text: str, n: int = 60) -> str:
    return text if len(text) <= n else text[:n] + "…"


def _depth(tree: ast.AST) -> int:
    """Nesting depth of ``tree``, computed without recursion."""
    deepest, stack = 0, [(tree, 1)]
    while stack:
        node, d = stack.pop()
        deepest = max(deepest, d)
        stack.extend((child, d + 1) for child in ast.iter_child_nodes(node))
    return deepest


class CostExprError(BtmissionError, ValueError):
    """The expression is not in the allowed grammar."""


@dataclass(frozen=True)
class CostExpr:
    """A parsed cost expression: its text, the task fields it reads and the calls it makes."""

    text: str
    symbols: tuple[str, ...]
    tree: ast.Expression

    def evaluate(
        self, call: Callable[[str, tuple[object, ...]], float], fields: Mapping[str, object]
    ) -> float:
        """Evaluate with ``call(function_name, argument_values)`` supplying path/straight costs.

        Raises :class:`CostExprError` on a division by zero or an overflow of finite numbers
        (an infinite path cost, no path, stays infinite)."""
        try:
            return _eval(self.tree.body, call, fields)
        except CostExprError as exc:
            raise CostExprError(f"{exc} in '{self.text}'") from None

    def probe(self, fields: Mapping[str, object]) -> str | None:
        """What goes wrong evaluating on a task's ``fields`` with every path or straight-line
        cost 1 and then 0 (an agent at the place): a division by zero, an overflow, a field that
        is not a number, a negative bid. None when nothing does (or a field is missing)."""
        if any(s not in fields for s in self.symbols):
            return None
        has_calls = any(isinstance(n, ast.Call) for n in ast.walk(self.tree))
        for value in (1.0, 0.0) if has_calls else (1.0,):

            def call(_name: str, _args: tuple[object, ...], v: float = value) -> float:
                return v

            when = f" when every path cost is {value:g}" if has_calls else ""
            try:
                cost = self.evaluate(call, fields)
            except CostExprError as exc:
                return f"{exc}{when}"
            if cost < 0:
                return f"'{self.text}' is {cost:g}{when}; bids must be ≥ 0"
        return None


def parse_cost(text: str) -> CostExpr:
    """Parse and check ``text``; raises :class:`CostExprError` with what is wrong.

    >>> parse_cost("path_cost(pickup) + path_cost(pickup, dropoff)").symbols
    ('dropoff', 'pickup')
    """
    if not isinstance(text, str) or not text.strip():
        raise CostExprError("expected a cost expression such as path_cost(location)")
    if len(text) > MAX_COST_CHARS:
        raise CostExprError(
            f"the expression is {len(text):,} characters long; the limit is {MAX_COST_CHARS:,}"
        )
    try:
        tree = ast.parse(text.strip(), mode="eval")
    except SyntaxError as exc:
        raise CostExprError(f"'{_short(text)}' is not a valid expression ({exc.msg})") from None
    except (RecursionError, MemoryError, ValueError):  # nesting the parser cannot hold; NUL
        raise CostExprError(f"'{_short(text)}' is not a valid expression") from None
    if _depth(tree) > MAX_COST_DEPTH:
        raise CostExprError(
            f"'{_short(text)}' nests more than {MAX_COST_DEPTH} operations deep; split the sum "
            "into fewer, larger terms"
        )
    symbols: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            if not isinstance(node.func, ast.Name) or node.func.id not in COST_FUNCTIONS:
                name = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
                raise CostExprError(
                    f"unknown function '{name}' in '{text}' (allowed: {', '.join(COST_FUNCTIONS)})"
                )
            lo, hi = COST_FUNCTIONS[node.func.id]
            if node.keywords or not lo <= len(node.args) <= hi:
                raise CostExprError(f"{node.func.id} takes {lo} or {hi} task fields, in '{text}'")
            for a in node.args:
                if not isinstance(a, ast.Name):
                    raise CostExprError(
                        f"{node.func.id} arguments must be task field names, in '{text}'"
                    )
        elif isinstance(node, ast.Name):
            if node.id not in COST_FUNCTIONS:
                symbols.add(node.id)
        elif isinstance(node, ast.BinOp):
            if type(node.op) not in _BINOPS:
                raise CostExprError(
                    f"operator {_OP_TEXT.get(type(node.op), type(node.op).__name__)} is not allowed "
                    f"in '{text}' (use + - * /)"
                )
        elif isinstance(node, ast.UnaryOp):
            if not isinstance(node.op, (ast.USub, ast.UAdd)):
                raise CostExprError(f"operator not allowed in '{text}'")
        elif isinstance(node, ast.Constant):
            if not isinstance(node.value, (int, float)) or isinstance(node.value, bool):
                raise CostExprError(f"only numbers may appear as constants in '{text}'")
            if not math.isfinite(node.value):
                raise CostExprError(f"a number in '{text}' is too large (not finite)")
        elif not isinstance(node, (ast.Expression, ast.Load, ast.operator, ast.unaryop)):
            raise CostExprError(f"'{ast.unparse(node)}' is not allowed in a cost expression")
    return CostExpr(text.strip(), tuple(sorted(symbols)), tree)


def _finite(value: float) -> float:
    if not math.isfinite(value):
        raise CostExprError(f"overflow (the value is {value})")
    return value


def _eval(
    node: ast.expr, call: Callable[[str, tuple[object, ...]], float], fields: Mapping[str, object]
) -> float:
    if isinstance(node, ast.Constant):
        assert isinstance(node.value, (int, float))  # parse_cost admits only numbers
        return float(node.value)
    if isinstance(node, ast.Name):
        value = fields[node.id]
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise CostExprError(f"task field '{node.id}' is not a number (got {value!r})")
        return _finite(float(value))
    if isinstance(node, ast.BinOp):
        left, right = _eval(node.left, call, fields), _eval(node.right, call, fields)
        if isinstance(node.op, ast.Div) and right == 0:
            raise CostExprError("division by zero")
        out = _BINOPS[type(node.op)](left, right)
        if math.isfinite(left) and math.isfinite(right):
            _finite(out)
        return out
    if isinstance(node, ast.UnaryOp):
        v = _eval(node.operand, call, fields)
        return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.Call):
        assert isinstance(node.func, ast.Name)
        args = tuple(fields[a.id] for a in node.args if isinstance(a, ast.Name))
        return float(call(node.func.id, args))
    raise CostExprError(f"cannot evaluate {ast.unparse(node)}")  # pragma: no cover - parse rejects
