"""Leaf substitution: run a mission with some leaves of the agents' trees replaced, for tests.

Modelled on BehaviorTree.CPP's substitution rules (``BehaviorTreeFactory::addSubstitutionRule``
with a wildcard pattern, and ``TestNodeConfig``: the status to return, an asynchronous delay, a
script run when it completes). A behaviour test that is about the auction, the commands or the
tree's logic need not fly a vehicle through D*+ and the NMPC: it replaces the leaves that fly by
leaves that answer at once (or after a while of mission time)::

    from py_trees.common import Status
    from btmission.runtime.substitution import TestLeaf

    run = MissionRun(mission, substitutions={
        "takeoff": TestLeaf(),                                   # SUCCESS at once
        "follow_path*": TestLeaf(after_s=5.0, effect=teleport),  # RUNNING for 5 s, then SUCCESS
        "R2/land": TestLeaf(Status.FAILURE, reason="motor fault"),
        "is_flying": lambda ctx: True,                           # a condition function
        "update_path": MyPlanner,                                # an action class
    })

**Patterns** are shell-style wildcards (:func:`fnmatch.fnmatchcase`: ``*``, ``?``, ``[abc]``),
matched against a leaf's **name** (``follow_path``) and its **label** (``follow_path(goal)``, the
name with its arguments as the tree shows them); a pattern with a ``/`` is matched against
``<agent>/<name>`` and ``<agent>/<label>`` (``R2/land``, ``H*/load*``). Rules are tried in order
and the **first** that matches a leaf replaces it. A rule that replaces no leaf of any agent's
tree (a typo, or every leaf it matches was taken by an earlier rule) is an error
(:class:`SubstitutionError`), raised before the run writes anything: a test that silently
substitutes nothing would test the wrong thing.

**Replacements**

* :class:`TestLeaf` — the test node: ``status`` (SUCCESS or FAILURE) after ``after_s`` seconds
  of mission time during which it is RUNNING, then ``effect(ctx, **args)`` (the leaf's bound
  arguments, like a condition's) just before it answers — to set a blackboard entry, or teleport
  a :mod:`fake <btmission.backends.fake>` vehicle to its goal. A FAILURE carries ``reason``
  (default: the rule that substituted it), and the task fails with it, as with a real action.
  On a condition it answers at once, every tick (no ``after_s``, no ``effect``: give a function
  for that).
* an action class (a :class:`~btmission.runtime.leaves.StatefulAction` subclass) — built like a
  library's action, with the leaf's node and the agent's context;
* a condition function ``fn(ctx, **args) -> bool`` — built like a library's condition.

Any replacement may take the place of an action or a condition leaf. The agent's built-in leaves
(``task_assigned``, ``idle_timeout``, ``wait``) are leaves too and may be substituted.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import py_trees
from py_trees.common import Status

from btmission.errors import BtmissionError
from btmission.runtime.leaves import AgentContext, Condition, ConditionLeaf, StatefulAction
from btmission.synthesis.tree import Kind, Node

if TYPE_CHECKING:
    from btmission.spec.mission import Mission

Effect = Callable[..., None]
"""``effect(ctx, **args)``: what a :class:`TestLeaf` does when it finishes."""


class SubstitutionError(BtmissionError, ValueError):
    """A substitution rule that cannot be used: a bad replacement, or one that replaces no leaf."""


@dataclass(frozen=True)
class TestLeaf:
    """A test node (BT.CPP's ``TestNodeConfig``): RUNNING for ``after_s`` seconds of mission
    time, then ``effect(ctx, **args)`` runs and the leaf returns ``status``; a FAILURE reports
    ``reason``."""

    __test__ = False  # not a pytest test class

    status: Status = Status.SUCCESS
    after_s: float = 0.0
    effect: Effect | None = None
    reason: str = ""

    def __post_init__(self) -> None:
        if self.status not in (Status.SUCCESS, Status.FAILURE):
            raise SubstitutionError(f"a test leaf returns SUCCESS or FAILURE, not {self.status}")
        if not self.after_s >= 0:
            raise SubstitutionError(f"after_s must be >= 0 s, got {self.after_s}")


Replacement = TestLeaf | type[StatefulAction] | Condition
"""What a rule puts in a leaf's place (module docstring)."""


@dataclass(frozen=True)
class Rule:
    """One substitution rule: leaves matching ``pattern`` become ``replacement``."""

    pattern: str
    replacement: Replacement

    def matches(self, agent: str, node: Node) -> bool:
        if "/" in self.pattern:
            names = (f"{agent}/{node.name}", f"{agent}/{node.label}")
        else:
            names = (node.name, node.label)
        return any(fnmatch.fnmatchcase(n, self.pattern) for n in names)


class TestAction(StatefulAction):
    """The leaf a :class:`TestLeaf` builds in an action's place."""

    __test__ = False

    def __init__(self, node: Node, ctx: AgentContext, rule: Rule) -> None:
        super().__init__(node, ctx)
        assert isinstance(rule.replacement, TestLeaf)
        self.rule = rule
        self.config: TestLeaf = rule.replacement
        self._t0 = 0.0

    def on_start(self) -> Status:
        self._t0 = self.ctx.now()
        return self.on_running()

    def on_running(self) -> Status:
        cfg = self.config
        if self.ctx.now() - self._t0 < cfg.after_s - 1e-9:
            return Status.RUNNING
        if cfg.effect is not None:
            cfg.effect(self.ctx, **self.args)
        if cfg.status is Status.FAILURE:
            self.reason = cfg.reason or f"substituted by rule '{self.rule.pattern}'"
        return cfg.status


SubstitutionRules = Mapping[str, Replacement] | Iterable[tuple[str, Replacement]]
"""Rules as a caller writes them: ``{pattern: replacement}`` or ``[(pattern, replacement)]``."""


class Substitutions:
    """Ordered substitution rules for one run (module docstring). Give :class:`MissionRun
    <btmission.runtime.runner.MissionRun>` (or :class:`~btmission.runtime.session.RunSession`)
    a mapping ``{pattern: replacement}``, a list of ``(pattern, replacement)`` pairs, or one of
    these."""

    def __init__(self, rules: SubstitutionRules = ()) -> None:
        pairs = rules.items() if isinstance(rules, Mapping) else rules
        self.rules: tuple[Rule, ...] = tuple(Rule(p, r) for p, r in pairs)
        for rule in self.rules:
            if not isinstance(rule.pattern, str) or not rule.pattern:
                raise SubstitutionError(
                    f"a rule's pattern is a non-empty string, got {rule.pattern!r}"
                )
            r = rule.replacement
            ok = (
                isinstance(r, TestLeaf)
                or (isinstance(r, type) and issubclass(r, StatefulAction))
                or (callable(r) and not isinstance(r, type))
            )
            if not ok:
                raise SubstitutionError(
                    f"rule '{rule.pattern}': the replacement must be a TestLeaf, a StatefulAction "
                    f"subclass or a condition function fn(ctx, **args) -> bool, got {r!r}"
                )

    @classmethod
    def of(
        cls,
        rules: Substitutions | SubstitutionRules | None,
    ) -> Substitutions | None:
        """``rules`` as :class:`Substitutions` (None or empty: None)."""
        if rules is None or isinstance(rules, Substitutions):
            return rules or None
        return cls(rules) or None

    def __bool__(self) -> bool:
        return bool(self.rules)

    def __len__(self) -> int:
        return len(self.rules)

    def rule_for(self, agent: str, node: Node) -> Rule | None:
        """The first rule that matches ``agent``'s leaf ``node`` (None: keep the leaf)."""
        return next((r for r in self.rules if r.matches(agent, node)), None)

    def leaf(
        self, agent: str, node: Node, ctx: AgentContext
    ) -> py_trees.behaviour.Behaviour | None:
        """The behaviour replacing ``node`` in ``agent``'s tree, or None if no rule matches it."""
        rule = self.rule_for(agent, node)
        if rule is None:
            return None
        r = rule.replacement
        if isinstance(r, TestLeaf):
            if node.kind is Kind.CONDITION:
                _check_condition(rule, node)
                answer = r.status is Status.SUCCESS
                return ConditionLeaf(node, lambda _ctx, **_args: answer, ctx)
            return TestAction(node, ctx, rule)
        if isinstance(r, type):
            action: StatefulAction = r(node, ctx)
            return action
        return ConditionLeaf(node, r, ctx)

    def check(self, mission: Mission) -> None:
        """Raise :class:`SubstitutionError` if a rule replaces no leaf of any agent's mission
        tree, or a test leaf with a delay or an effect would replace a condition."""
        from btmission.synthesis.mission_tree import build_mission_tree

        used: set[int] = set()
        names: set[str] = set()
        for agent in mission.agents:
            for node in _leaves(build_mission_tree(mission, agent.id).tree):
                names.add(node.label)
                rule = self.rule_for(agent.id, node)
                if rule is None:
                    continue
                used.add(id(rule))
                if isinstance(rule.replacement, TestLeaf) and node.kind is Kind.CONDITION:
                    _check_condition(rule, node)
        unused = [r for r in self.rules if id(r) not in used]
        if unused:
            shown = ", ".join(sorted(names)[:20]) + (" ..." if len(names) > 20 else "")
            raise SubstitutionError(
                "substitution rule(s) "
                + ", ".join(f"'{r.pattern}'" for r in unused)
                + " replace no leaf of any agent's tree (the pattern matches no leaf's name or "
                f"label, or an earlier rule took every leaf it matches); the leaves are: {shown}"
            )


def _check_condition(rule: Rule, node: Node) -> None:
    r = rule.replacement
    assert isinstance(r, TestLeaf)
    if r.after_s > 0 or r.effect is not None:
        raise SubstitutionError(
            f"rule '{rule.pattern}' replaces the condition '{node.label}' with a test leaf that "
            "has an after_s delay or an effect: a condition answers at once (give a function "
            "fn(ctx, **args) -> bool instead)"
        )


def _leaves(root: Node) -> Iterator[Node]:
    stack = [root]
    while stack:
        node = stack.pop()
        if node.is_leaf:
            yield node
        else:
            stack.extend(node.children)
