"""Capability libraries (DESIGN.md §4.1): the schema users write and the checked model synthesis reads.

A library declares *conditions* (with named parameters) and *actions* with pre- and
postconditions, following the library ``L = {A_i, A^Pre_ij, A^Post_ik}`` of seed 000 §IV-A
(Table I). Loading happens in two steps:

1. :class:`LibrarySpec` (pydantic) checks the file's shape: keys, types, names.
2. :func:`compile_library` resolves every reference (``has_path(goal)``) against the declared
   conditions and binds its arguments to the action's parameters or library variables, producing the
   immutable :class:`Library`. Problems are collected, each with its file:line, never just the first.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, field_validator

from btmission.diagnostics import Diagnostic, Location, Severity, SpecError, errors
from btmission.spec.common import DottedName, FiniteFloat, FormatVersion, Identifier, validate_model
from btmission.spec.refs import Ref, RefSyntaxError, parse_ref
from btmission.spec.source import Source, parse_yaml, read_yaml

LIBRARY_FORMAT_VERSION = 1

BTCPP_RESERVED_PARAMS = frozenset({"name", "ID"})
BTCPP_BUILTIN_NODES = frozenset(
    {
        # node types BT.CPP 4.x registers itself (bt_factory.cpp); a leaf cannot reuse them
        "AlwaysFailure", "AlwaysSuccess", "AsyncFallback", "AsyncSequence", "Delay",
        "Fallback", "ForceFailure", "ForceSuccess", "IfThenElse", "Inverter",
        "KeepRunningUntilFailure", "LoopBool", "LoopDouble", "LoopInt", "LoopString",
        "Parallel", "ParallelAll", "Precondition", "ReactiveFallback", "ReactiveSequence",
        "Repeat", "RetryUntilSuccessful", "RunOnce", "Script", "ScriptCondition",
        "SequenceWithMemory", "SequenceStar", "Sequence", "SetBlackboard", "SkipUnlessUpdated",
        "Sleep", "SubTree", "Switch2", "Switch3", "Switch4", "Switch5", "Switch6", "Timeout",
        "TryCatch", "UnsetBlackboard", "WaitValueUpdate", "WasEntryUpdated", "WhileDoElse",
        "BlackboardCheckBool", "BlackboardCheckDouble", "BlackboardCheckInt",
        "BlackboardCheckString", "ManualSelector",
        # element names with a meaning of their own in the XML
        "Action", "Condition", "Control", "Decorator", "BehaviorTree", "TreeNodesModel",
        "include", "root",
    }
)  # fmt: skip
"""IDs a leaf may not have: BT.CPP's own node types and the XML format's special elements."""

RESERVED_NAMES = frozenset({"task_assigned", "idle_timeout", "wait"})
"""Leaves the runtime provides in every mission tree (seed 000 Fig. 7); libraries cannot reuse them."""


# --------------------------------------------------------------------------------------------
# 1. The file's schema
# --------------------------------------------------------------------------------------------
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ConditionSpec(_Strict):
    """A condition the platform can check, e.g. ``at_goal: {doc: ..., params: [goal]}``."""

    doc: str = Field("", description="What the condition means, in one line.")
    params: list[Identifier] = Field(
        default_factory=list, description="Named parameters, in order."
    )


class VariableSpec(_Strict):
    """A named value the implementations keep on the blackboard (e.g. ``home``)."""

    doc: str = Field("", description="What the variable holds and who sets it.")


class ActionSpec(_Strict):
    """An action with its preconditions and the postconditions it achieves."""

    doc: str = Field("", description="What the action does, in one line.")
    params: list[Identifier] = Field(
        default_factory=list, description="Named parameters, in order."
    )
    pre: list[str] = Field(
        default_factory=list,
        description="Conditions that must hold before the action runs, in tick order, e.g. has_path(goal).",
    )
    post: list[str] = Field(
        default_factory=list, description="Conditions the action makes true, e.g. at_goal(goal)."
    )
    cost: FiniteFloat = Field(
        1.0,
        ge=0,
        description="Preference when several actions achieve one condition: the lowest cost wins, "
        "then declaration order.",
    )


def _entry_kind(v: Any) -> str:
    return "Doc" if isinstance(v, str) else "Null" if v is None else "Spec"


ConditionEntry = Annotated[
    Annotated[ConditionSpec, Tag("Spec")]
    | Annotated[str, Tag("Doc")]
    | Annotated[None, Tag("Null")],
    Discriminator(_entry_kind),
]
"""A condition: its full form, or just its doc string, or nothing."""

VariableEntry = Annotated[
    Annotated[VariableSpec, Tag("Spec")]
    | Annotated[str, Tag("Doc")]
    | Annotated[None, Tag("Null")],
    Discriminator(_entry_kind),
]


class LibrarySpec(_Strict):
    """A capability library file (``version: 1``)."""

    library: Identifier = Field(description="The library's name, used to refer to it.")
    version: FormatVersion = Field(description="File format version; must be 1.")
    description: str = ""
    module: DottedName | None = Field(
        None,
        description="Python module with the implementations (optional: without it the "
        "library synthesises and exports but cannot run).",
    )
    variables: dict[Identifier, VariableEntry] = Field(
        default_factory=dict,
        description="Blackboard values the implementations provide that references may name "
        "(e.g. home).",
    )
    goals: list[str] = Field(
        default_factory=list,
        description="Goals this library is built for; `library check` synthesises them and warns "
        "about actions none of them uses.",
    )
    conditions: dict[Identifier, ConditionEntry] = Field(
        description='Conditions by name; `name: "doc text"` is short for `name: {doc: ...}`.'
    )
    actions: dict[Identifier, ActionSpec | None] = Field(description="Actions by name.")

    @field_validator("conditions", "variables", "actions", mode="before")
    @classmethod
    def _empty_mapping(cls, v: object) -> object:
        """An empty section (``conditions:`` with nothing under it) is an empty mapping."""
        return {} if v is None else v


# --------------------------------------------------------------------------------------------
# 2. The checked model
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, slots=True)
class Atom:
    """A condition with its arguments bound to symbols, e.g. ``at_goal(location)``."""

    name: str
    args: tuple[str, ...] = ()

    def __str__(self) -> str:
        return f"{self.name}({', '.join(self.args)})" if self.args else self.name

    def substitute(self, binding: Mapping[str, str]) -> Atom:
        """Replace symbols by their bound value (symbols without a binding stay as they are)."""
        if not self.args:
            return self
        return Atom(self.name, tuple(binding.get(a, a) for a in self.args))


@dataclass(frozen=True)
class Condition:
    name: str
    params: tuple[str, ...] = ()
    doc: str = ""
    where: Location = Location()


@dataclass(frozen=True)
class Action:
    """A checked action. ``pre``/``post`` arguments are the action's params or library variables."""

    name: str
    params: tuple[str, ...] = ()
    pre: tuple[Atom, ...] = ()
    post: tuple[Atom, ...] = ()
    cost: float = 1.0
    index: int = 0  # declaration order, the tie-breaker after cost
    doc: str = ""
    where: Location = Location()
    pre_where: tuple[Location, ...] = ()

    def __str__(self) -> str:
        return f"{self.name}({', '.join(self.params)})" if self.params else self.name


@dataclass(frozen=True)
class Library:
    """A checked capability library: what synthesis, the checks and the runtime read."""

    name: str
    version: int
    description: str
    module: str | None
    conditions: Mapping[str, Condition]
    actions: Mapping[str, Action]
    variables: Mapping[str, str]
    goals: tuple[Atom, ...] = ()
    file: str | None = None
    goal_where: tuple[Location, ...] = ()
    achievers: Mapping[str, tuple[tuple[Action, Atom], ...]] = field(default_factory=dict)
    """condition name → every (action, postcondition pattern) that can make it true, best first."""

    def where(self, item: str) -> Location:
        """Location of an action or condition definition (falls back to the file)."""
        if item in self.actions:
            return self.actions[item].where
        if item in self.conditions:
            return self.conditions[item].where
        return Location(self.file)


def _bind(ref: Ref, cond: Condition, ctx: str) -> tuple[tuple[str, ...] | None, str | None]:
    """Order ``ref``'s arguments as ``cond``'s params. Returns (args, error message)."""
    if len(ref.args) > len(cond.params):
        return None, (
            f"{ctx}'{ref}' gives {len(ref.args) + len(ref.kwargs)} argument(s) but condition "
            f"'{cond.name}' takes {len(cond.params)} ({_plist(cond.params)})"
        )
    bound: dict[str, str] = dict(zip(cond.params, ref.args))
    for k, v in ref.kwargs:
        if k not in cond.params:
            return (
                None,
                f"{ctx}'{ref}': condition '{cond.name}' has no parameter '{k}' ({_plist(cond.params)})",
            )
        if k in bound:
            return None, f"{ctx}'{ref}': parameter '{k}' given twice"
        bound[k] = v
    missing = [p for p in cond.params if p not in bound]
    if missing:
        return None, (
            f"{ctx}'{ref}' leaves parameter(s) {', '.join(missing)} of '{cond.name}' unbound "
            f"(expected {cond.name}({', '.join(cond.params)}))"
        )
    return tuple(bound[p] for p in cond.params), None


def _plist(params: Sequence[str]) -> str:
    return f"params: {', '.join(params)}" if params else "no params"


def resolve_ref(
    text: str,
    conditions: Mapping[str, Condition],
    allowed_symbols: set[str] | None,
    ctx: str = "",
) -> tuple[Atom | None, str | None, str]:
    """Parse and bind one reference. ``allowed_symbols`` None means any symbol is accepted.

    Returns (atom, error message, error code).
    """
    try:
        ref = parse_ref(text)
    except RefSyntaxError as exc:
        return None, str(exc), "ref-syntax"
    cond = conditions.get(ref.name)
    if cond is None:
        hint = _suggest(ref.name, conditions)
        return None, f"{ctx}undefined condition '{ref.name}'{hint}", "undefined-condition"
    args, err = _bind(ref, cond, ctx)
    if err or args is None:
        return None, err, "bad-arguments"
    if allowed_symbols is not None:
        for a in args:
            if a not in allowed_symbols:
                allowed = ", ".join(sorted(allowed_symbols)) or "none"
                return (
                    None,
                    (f"{ctx}'{text}' uses undefined parameter '{a}' (known here: {allowed})"),
                    "undefined-parameter",
                )
    return Atom(ref.name, args), None, ""


def _suggest(name: str, known: Mapping[str, object]) -> str:
    import difflib

    close = difflib.get_close_matches(name, list(known), n=1)
    return f" (did you mean '{close[0]}'?)" if close else ""


def compile_library(
    spec: LibrarySpec, src: Source | None = None
) -> tuple[Library, list[Diagnostic]]:
    """Resolve references and build the :class:`Library`; returns it with every problem found.

    Items with errors are kept out of the model (so checks can still run on the rest); callers that
    need a usable library must refuse it when the diagnostics contain errors.
    """
    file = src.file if src else None
    diags: list[Diagnostic] = []

    def loc(*path: str | int) -> Location:
        if not src:
            return Location(file)
        # definitions point at their name; references and values at the value itself
        return src.locate(path, key=len(path) == 2)

    def err(path: tuple[str | int, ...], message: str, code: str) -> None:
        from btmission.spec.source import format_path

        diags.append(Diagnostic(Severity.ERROR, code, message, format_path(path), loc(*path)))

    conditions: dict[str, Condition] = {}

    def warn_btcpp(path: tuple[str | int, ...], params: Sequence[str]) -> None:
        from btmission.spec.source import format_path

        kind, leaf = str(path[0])[:-1], str(path[1])
        if leaf in BTCPP_BUILTIN_NODES:
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "btcpp-reserved",
                    f"{kind} '{leaf}' has the name of one of BehaviorTree.CPP's own node types or "
                    "XML elements: the tree synthesises but cannot be exported with -f xml",
                    format_path(path[:2]),
                    loc(*path[:2]),
                )
            )
        bad = [p for p in params if p in BTCPP_RESERVED_PARAMS or p.startswith("_")]
        if bad:
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "btcpp-reserved",
                    f"parameter(s) {', '.join(bad)} are reserved attribute names in BehaviorTree.CPP "
                    "XML: the tree synthesises but cannot be exported with -f xml",
                    format_path(path),
                    loc(*path),
                )
            )

    for cname, centry in spec.conditions.items():
        cspec = ConditionSpec(doc=centry) if isinstance(centry, str) else centry or ConditionSpec()
        warn_btcpp(("conditions", cname, "params"), cspec.params)
        if len(set(cspec.params)) != len(cspec.params):
            err(
                ("conditions", cname, "params"), "parameter names must be unique", "duplicate-param"
            )
        conditions[cname] = Condition(
            cname, tuple(cspec.params), cspec.doc, loc("conditions", cname)
        )
    variables = {
        k: (v if isinstance(v, str) else v.doc if v else "") for k, v in spec.variables.items()
    }
    for k in variables:
        if k in conditions or k in spec.actions:
            err(
                ("variables", k),
                f"variable '{k}' has the same name as a condition or action",
                "name-clash",
            )
    for name in sorted(RESERVED_NAMES & (set(conditions) | set(spec.actions))):
        kind = "conditions" if name in conditions else "actions"
        err(
            (kind, name),
            f"'{name}' is reserved for the mission tree's built-in leaves",
            "reserved-name",
        )
    for a in spec.actions:
        if a in conditions:
            err(("actions", a), f"action '{a}' has the same name as a condition", "name-clash")

    actions: dict[str, Action] = {}
    for index, (aname, aentry) in enumerate(spec.actions.items()):
        aspec = aentry or ActionSpec()
        warn_btcpp(("actions", aname, "params"), aspec.params)
        params = tuple(aspec.params)
        if len(set(params)) != len(params):
            err(("actions", aname, "params"), "parameter names must be unique", "duplicate-param")
        shadow = [p for p in params if p in variables]
        if shadow:
            err(
                ("actions", aname, "params"),
                f"parameter(s) {', '.join(shadow)} shadow library variables",
                "name-clash",
            )
        symbols = set(params) | set(variables)
        ok = True
        lists: dict[str, list[Atom]] = {"pre": [], "post": []}
        pre_where: list[Location] = []
        for key in ("pre", "post"):
            for i, text in enumerate(getattr(aspec, key)):
                atom, message, code = resolve_ref(text, conditions, symbols)
                if atom is None:
                    err(("actions", aname, key, i), message or "invalid reference", code)
                    ok = False
                    continue
                lists[key].append(atom)
                if key == "pre":
                    pre_where.append(loc("actions", aname, key, i))
        for i, atom in enumerate(lists["post"]):
            unbound = [p for p in params if p not in atom.args]
            if unbound:
                err(
                    ("actions", aname, "post", i),
                    f"postcondition '{atom}' does not bind parameter(s) {', '.join(unbound)} of "
                    f"action '{aname}': back-chaining through it could not know their values",
                    "unbound-parameter",
                )
                ok = False
        if not aspec.post:
            diags.append(
                Diagnostic(
                    Severity.WARNING,
                    "unreachable-action",
                    f"action '{aname}' has no postconditions, so back-chaining can never choose it",
                    f"actions.{aname}",
                    loc("actions", aname),
                )
            )
        if ok:
            actions[aname] = Action(
                aname,
                params,
                tuple(lists["pre"]),
                tuple(lists["post"]),
                aspec.cost,
                index,
                aspec.doc,
                loc("actions", aname),
                tuple(pre_where),
            )

    goals: list[Atom] = []
    goal_where: list[Location] = []
    for i, text in enumerate(spec.goals):
        atom, message, code = resolve_ref(text, conditions, None)
        if atom is None:
            err(("goals", i), message or "invalid goal", code)
            continue
        goals.append(atom)
        goal_where.append(loc("goals", i))

    achievers: dict[str, list[tuple[Action, Atom]]] = {}
    for act in actions.values():
        for post in act.post:
            achievers.setdefault(post.name, []).append((act, post))
    ordered = {
        c: tuple(sorted(lst, key=lambda ap: (ap[0].cost, ap[0].index)))
        for c, lst in achievers.items()
    }
    lib = Library(
        name=spec.library,
        version=spec.version,
        description=spec.description,
        module=spec.module,
        conditions=conditions,
        actions=actions,
        variables=variables,
        goals=tuple(goals),
        file=file,
        goal_where=tuple(goal_where),
        achievers=ordered,
    )
    return lib, diags


def load_library_source(src: Source) -> tuple[Library, list[Diagnostic]]:
    """Schema-check and compile a parsed library document (schema errors raise SpecError)."""
    spec = validate_model(LibrarySpec, src, "library")
    return compile_library(spec, src)


def load_library_file(path: str | Path) -> tuple[Library, list[Diagnostic]]:
    """Read, schema-check and compile a library file. Returns the library and its findings."""
    return load_library_source(read_yaml(path))


def load_library_text(text: str, file: str = "<input>") -> tuple[Library, list[Diagnostic]]:
    """Like :func:`load_library_file` for YAML text (tests, generated libraries)."""
    return load_library_source(parse_yaml(text, file))


def require_usable(lib: Library, diags: Sequence[Diagnostic]) -> Library:
    """Raise :class:`SpecError` when ``diags`` contain errors, else return ``lib``."""
    errs = errors(diags)
    if errs:
        raise SpecError(errs)
    return lib
