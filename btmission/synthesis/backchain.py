"""Back-chaining synthesis of a fully expanded behaviour tree (seed 000 §IV-A, Alg. 1 and 2).

Algorithm 1 starts from the goal condition and, while some condition C in the tree can be expanded,
applies Algorithm 2::

    A      ← FindActionThatSolvesCondition(C)
    T1     ← Sequence([A^Pre_1, …, A^Pre_n], A)
    T2     ← Fallback(C, T1)
    BT     ← Replace(BT, C, T2)

until no condition is left to expand. Every condition is expanded before deployment (the paper's
key difference from reactive back-chaining), so an infeasible task is found up front.

Implementation notes (behaviour identical to the loop above, but linear in the library size):

* The expansion of a *ground* condition (name + bound symbols) does not depend on where it occurs,
  so it is computed once and the resulting immutable subtree is shared by every occurrence
  (memoisation keyed by :class:`Atom`). Exports and py_trees expand the sharing.
* The expansion is an explicit-stack depth-first search, so 10,000-deep chains need no recursion.
  A precondition that is already being expanded further up the stack is a *cycle*: it is reported
  with its chain of names and left as an unexpanded leaf (role ``CYCLE``).
* A condition no action achieves stays a plain condition leaf and is reported as *assumed*.
* When several actions achieve a condition, the lowest declared ``cost`` wins, then declaration
  order; the choice is reported, and an exact tie is reported as *ambiguous*.
* If an action has no preconditions, ``Sequence([], A)`` is written as ``A`` itself (a one-child
  sequence is equivalent and only adds a node), so ``Fallback(C, A)``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from btmission.diagnostics import Diagnostic, Location, Severity, errors, promote
from btmission.spec.library import Action, Atom, Library, resolve_ref
from btmission.synthesis.tree import Arg, Kind, Node, Role, count_nodes, walk, walk_distinct

DEFAULT_MAX_NODES = 2_000_000


@dataclass(frozen=True)
class Choice:
    """Which action was chosen to achieve a ground condition, and what else could have."""

    atom: Atom
    chosen: Action
    candidates: tuple[Action, ...]

    @property
    def tie(self) -> bool:
        return sum(1 for a in self.candidates if a.cost == self.chosen.cost) > 1


@dataclass
class Synthesis:
    """The result of synthesising one goal (or a conjunction of goals)."""

    tree: Node
    goals: tuple[Atom, ...]
    diagnostics: list[Diagnostic]
    choices: dict[Atom, Choice] = field(default_factory=dict)
    assumed: tuple[Atom, ...] = ()
    used_actions: frozenset[str] = frozenset()
    inputs: tuple[str, ...] = ()
    """Free symbols the tree reads: task fields / blackboard keys it needs at run time."""
    size: int = 0

    @property
    def ok(self) -> bool:
        return not errors(self.diagnostics)


@dataclass
class _Frame:
    atom: Atom
    where: Location
    action: Action | None = None
    binding: dict[str, str] = field(default_factory=dict)
    pre: list[Atom] = field(default_factory=list)
    i: int = 0
    cycle_leaves: dict[int, Node] = field(default_factory=dict)


def match(action: Action, pattern: Atom, atom: Atom) -> dict[str, str] | None:
    """Bind ``action``'s parameters so that its postcondition ``pattern`` equals ``atom``.

    Pattern arguments that are action parameters bind to the required symbol; other arguments are
    library variables and must equal it. Returns None when the postcondition cannot give ``atom``.
    """
    if pattern.name != atom.name or len(pattern.args) != len(atom.args):
        return None
    binding: dict[str, str] = {}
    params = action.params
    for p, v in zip(pattern.args, atom.args):
        if p in params:
            if binding.setdefault(p, v) != v:
                return None
        elif p != v:
            return None
    return binding


class Synthesizer:
    """Back-chains goals over one library, memoising expansions across calls.

    One instance serves many goals (the library check synthesises every condition with one), and the
    memo guarantees each ground condition is expanded once.
    """

    def __init__(self, library: Library) -> None:
        self.library = library
        self._memo: dict[Atom, Node] = {}
        self._choices: dict[Atom, Choice] = {}
        self._assumed: dict[Atom, Location] = {}
        self._cycles: dict[frozenset[Atom], Diagnostic] = {}
        self._cond_leaf: dict[Atom, Node] = {}

    # -- leaves ------------------------------------------------------------------------------
    def condition_leaf(self, atom: Atom, role: Role = Role.PLAIN) -> Node:
        if role is Role.PLAIN and atom in self._cond_leaf:
            return self._cond_leaf[atom]
        cond = self.library.conditions[atom.name]
        node = Node(
            Kind.CONDITION,
            atom.name,
            tuple(Arg(p, v) for p, v in zip(cond.params, atom.args)),
            (),
            role,
            cond.doc,
        )
        if role is Role.PLAIN:
            self._cond_leaf[atom] = node
        return node

    def action_leaf(self, action: Action, binding: dict[str, str]) -> Node:
        return Node(
            Kind.ACTION,
            action.name,
            tuple(Arg(p, binding[p]) for p in action.params),
            (),
            Role.PLAIN,
            action.doc,
        )

    # -- Alg. 2 line 2: FindActionThatSolvesCondition -----------------------------------------
    def choose(self, atom: Atom) -> tuple[Action, dict[str, str]] | None:
        """The best action achieving ``atom`` (lowest cost, then declaration order) and its binding."""
        found: list[tuple[Action, dict[str, str]]] = []
        for act, pattern in self.library.achievers.get(atom.name, ()):
            b = match(act, pattern, atom)
            if b is not None and all(a is not act for a, _ in found):
                found.append((act, b))
        if not found:
            return None
        if len(found) > 1:
            self._choices[atom] = Choice(atom, found[0][0], tuple(a for a, _ in found))
        return found[0]

    # -- Alg. 1 / 2 ----------------------------------------------------------------------------
    def expand(self, goal: Atom, where: Location | None = None) -> Node:
        """The fully expanded PPA subtree that ensures ``goal``."""
        if goal in self._memo:
            return self._memo[goal]
        stack: list[_Frame] = [_Frame(goal, where or Location(self.library.file))]
        on_path: dict[Atom, int] = {}
        while stack:
            f = stack[-1]
            if f.action is None and f.i == 0 and f.atom not in on_path:
                chosen = self.choose(f.atom)
                if chosen is None:
                    self._assumed.setdefault(f.atom, f.where)
                    self._memo[f.atom] = self.condition_leaf(f.atom, Role.ASSUMED)
                    stack.pop()
                    continue
                f.action, f.binding = chosen
                f.pre = [p.substitute(f.binding) for p in f.action.pre]
                on_path[f.atom] = len(stack) - 1
            assert f.action is not None
            if f.i < len(f.pre):
                idx = f.i
                p = f.pre[idx]
                f.i += 1
                if p in self._memo:
                    continue
                pwhere = (
                    f.action.pre_where[idx] if idx < len(f.action.pre_where) else f.action.where
                )
                if p in on_path:
                    f.cycle_leaves[idx] = self.condition_leaf(p, Role.CYCLE)
                    self._report_cycle(stack, on_path[p], p, pwhere)
                    continue
                stack.append(_Frame(p, pwhere))
                continue
            # all preconditions expanded: T1 = Sequence(pre…, A); T2 = Fallback(C, T1)
            act_node = self.action_leaf(f.action, f.binding)
            if f.pre:
                kids = [f.cycle_leaves.get(k) or self._memo[p] for k, p in enumerate(f.pre)]
                t1 = Node(
                    Kind.SEQUENCE,
                    _seq_name(f.action, f.binding),
                    (),
                    (*kids, act_node),
                    Role.ACHIEVE,
                )
            else:
                t1 = act_node
            t2 = Node(Kind.FALLBACK, str(f.atom), (), (self.condition_leaf(f.atom), t1), Role.GOAL)
            self._memo[f.atom] = t2
            del on_path[f.atom]
            stack.pop()
        return self._memo[goal]

    def _report_cycle(
        self, stack: list[_Frame], start: int, closing: Atom, where: Location
    ) -> None:
        frames = stack[start:]
        key = frozenset(fr.atom for fr in frames)
        if key in self._cycles:
            return
        steps = []
        for fr in frames:
            assert fr.action is not None
            steps.append(f"{fr.atom} (by {fr.action.name})")
        chain = " needs ".join(steps) + f" needs {closing}"
        self._cycles[key] = Diagnostic(
            Severity.ERROR,
            "cycle",
            f"cycle between pre- and postconditions: {chain}",
            f"actions.{frames[-1].action.name}" if frames[-1].action else "",
            where,
        )

    def expansions(self) -> tuple[Node, ...]:
        """Every subtree expanded so far (one per ground condition), in expansion order."""
        return tuple(self._memo.values())

    # -- results -------------------------------------------------------------------------------
    def synthesize(
        self,
        goals: Sequence[Atom],
        goal_where: Sequence[Location] = (),
        *,
        strict: bool = False,
        max_nodes: int = DEFAULT_MAX_NODES,
    ) -> Synthesis:
        """Synthesise the tree for ``goals`` (several goals run in sequence, in the given order)."""
        if not goals:
            raise ValueError("synthesis needs at least one goal")
        wheres = list(goal_where) + [Location(self.library.file)] * (len(goals) - len(goal_where))
        roots = [self.expand(g, w) for g, w in zip(goals, wheres)]
        tree = (
            roots[0]
            if len(roots) == 1
            else Node(Kind.SEQUENCE, "goals", (), tuple(roots), Role.ACHIEVE)
        )
        return self.result(tree, tuple(goals), strict=strict, max_nodes=max_nodes)

    def result(
        self,
        tree: Node,
        goals: tuple[Atom, ...],
        *,
        strict: bool = False,
        max_nodes: int | None = DEFAULT_MAX_NODES,
    ) -> Synthesis:
        """Collect the findings that concern ``tree`` (a subset of everything expanded so far).

        ``max_nodes=None`` skips counting the expanded size (``size`` is then 0): the library check
        uses it for its synthetic all-conditions tree, whose expansion is never built.
        """
        distinct = [n for _, n in walk_distinct(tree)]
        used = frozenset(n.name for n in distinct if n.kind is Kind.ACTION and n.role is Role.PLAIN)
        atoms_in_tree = {
            Atom(n.name, tuple(a.value for a in n.args))
            for n in distinct
            if n.kind is Kind.CONDITION
        }
        diags: list[Diagnostic] = []
        for key, d in self._cycles.items():
            if key & atoms_in_tree:
                diags.append(d)
        assumed = tuple(a for a in self._assumed if a in atoms_in_tree)
        for a in assumed:
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "assumed-condition",
                    f"'{a}' is assumed: no action achieves it, so the tree only checks it",
                    a.name,
                    self._assumed[a],
                )
            )
        choices = {a: c for a, c in self._choices.items() if a in atoms_in_tree}
        diags.extend(_choice_diagnostics(choices.values(), self.library))
        size = count_nodes(tree) if max_nodes is not None else 0
        if max_nodes is not None and size > max_nodes:
            diags.append(
                Diagnostic(
                    Severity.ERROR,
                    "tree-too-large",
                    f"the expanded tree has {size} nodes (limit {max_nodes}); shared preconditions are "
                    "expanded at every occurrence — split the goal or raise the limit",
                    "",
                    Location(self.library.file),
                )
            )
        variables = set(self.library.variables)
        inputs = sorted(
            {
                a.value
                for n in distinct
                if n.is_leaf
                for a in n.args
                if not a.literal and a.value not in variables
            }
        )
        return Synthesis(
            tree=tree,
            goals=goals,
            diagnostics=promote(diags, strict),
            choices=choices,
            assumed=assumed,
            used_actions=used,
            inputs=tuple(inputs),
            size=size,
        )


def _seq_name(action: Action, binding: dict[str, str]) -> str:
    return (
        f"{action.name}({', '.join(binding[p] for p in action.params)})"
        if action.params
        else action.name
    )


def _choice_diagnostics(choices: Iterable[Choice], library: Library) -> list[Diagnostic]:
    out: list[Diagnostic] = []
    reported: set[tuple[str, str]] = set()
    for c in choices:
        key = (c.atom.name, c.chosen.name)
        if key in reported:
            continue
        reported.add(key)
        options = ", ".join(f"{a.name} (cost {a.cost:g})" for a in c.candidates)
        if c.tie:
            out.append(
                Diagnostic(
                    Severity.WARNING,
                    "ambiguous-achiever",
                    f"'{c.atom}' can be achieved by {options} with equal cost; chose {c.chosen.name} "
                    "(declared first) — give the preferred action a lower cost",
                    c.atom.name,
                    library.where(c.chosen.name),
                )
            )
        else:
            out.append(
                Diagnostic(
                    Severity.INFO,
                    "choice",
                    f"'{c.atom}' can be achieved by {options}; chose {c.chosen.name} (lowest cost)",
                    c.atom.name,
                    library.where(c.chosen.name),
                )
            )
    return out


def parse_goals(texts: Sequence[str], library: Library, option: str = "--goal") -> list[Atom]:
    """Resolve goal references (free symbols allowed: they become tree inputs).

    Raises :class:`btmission.diagnostics.SpecError` listing every bad goal.
    """
    from btmission.diagnostics import SpecError

    atoms: list[Atom] = []
    bad: list[Diagnostic] = []
    for i, text in enumerate(texts):
        atom, message, code = resolve_ref(text, library.conditions, None)
        if atom is None:
            bad.append(
                Diagnostic(
                    Severity.ERROR,
                    code,
                    message or "bad goal",
                    f"{option}[{i}]" if len(texts) > 1 else option,
                    Location("<command line>"),
                )
            )
        else:
            atoms.append(atom)
    if bad:
        raise SpecError(bad)
    return atoms


def synthesize(library: Library, goals: Sequence[Atom | str], *, strict: bool = False) -> Synthesis:
    """Synthesise the fully expanded tree for ``goals`` (Atom objects or reference strings)."""
    atoms = [g if isinstance(g, Atom) else parse_goals([g], library)[0] for g in goals]
    return Synthesizer(library).synthesize(atoms, strict=strict)


def iter_leaves(tree: Node) -> Iterable[Node]:
    """Every leaf occurrence in tick order."""
    return (n for _, n in walk(tree) if n.is_leaf)
