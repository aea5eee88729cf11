"""``btmission library``: list, show, check and scaffold capability libraries."""

from __future__ import annotations

import json
from pathlib import Path

import click

from btmission.cli.common import (
    ChecksFailed,
    checking_imports,
    echo_diagnostics,
    handle_spec_errors,
    output_target,
    with_implementations_option,
)
from btmission.diagnostics import errors
from btmission.plugins import library_catalog, load_library
from btmission.spec.common import shown
from btmission.synthesis.checks import check_library


@click.group()
def library() -> None:
    """Capability libraries: list, show, check, scaffold a plugin.

    A library is named by its installed name (entry-point group btmission.libraries) or by a path
    to its YAML file.
    """


@library.command("list")
@click.option("--json", "as_json", is_flag=True, help="Machine-readable output.")
def list_cmd(as_json: bool) -> None:
    """List installed libraries (built-in and plugins)."""
    rows: list[dict[str, object]] = []
    for name, item in library_catalog().items():
        if isinstance(item, Exception):
            rows.append({"name": name, "error": str(item)})
            continue
        lib = item.library
        impl = item.implementations
        total = len(lib.actions) + len(lib.conditions)
        n_impl = total - len(impl.missing(lib)) if impl else 0
        rows.append(
            {
                "name": name,
                "version": lib.version,
                "actions": len(lib.actions),
                "conditions": len(lib.conditions),
                "implemented": n_impl,
                "description": lib.description,
                "origin": item.origin,
            }
        )
    if as_json:
        click.echo(json.dumps(rows, indent=2))
        return
    if not rows:
        click.echo("no libraries installed")
        return
    width = max(len(str(r["name"])) for r in rows)
    for r in rows:
        if "error" in r:
            click.echo(f"{r['name']:<{width}}  ERROR: {r['error']}")
            continue
        total = int(r["actions"]) + int(r["conditions"])  # type: ignore[call-overload]
        runnable = (
            "runnable" if r["implemented"] == total else f"{r['implemented']}/{total} implemented"
        )
        click.echo(
            f"{r['name']:<{width}}  {r['actions']:>3} actions {r['conditions']:>3} conditions  "
            f"[{runnable}]  {r['description']}"
        )


@library.command("show")
@click.argument("ref")
@with_implementations_option
@handle_spec_errors
def show_cmd(ref: str, with_implementations: bool) -> None:
    """Show a library's variables, settings, conditions and actions (pre → post).

    A library given by path is shown without importing its implementation module (checking
    never runs plugin code); --with-implementations imports it and marks what is implemented.
    """
    with checking_imports(with_implementations):
        loaded = load_library(ref)
    lib = loaded.library
    impl = loaded.implementations
    click.echo(f"library {lib.name} (version {lib.version}) from {loaded.origin}")
    if lib.description:
        click.echo(f"  {lib.description}")
    click.echo(
        f"  module: {lib.module or '-'}"
        + (f"  ({loaded.import_error})" if loaded.import_error else "")
        + (
            "  (not imported; --with-implementations imports it)"
            if loaded.module_not_imported
            else ""
        )
    )
    if lib.variables:
        click.echo("variables:")
        for k, doc in lib.variables.items():
            click.echo(f"  {k:<18} {doc}")
    if impl and impl.declared:  # what a mission may set under runtime.settings, as declared
        click.echo("settings:")
        width = max(18, *(len(name) for name in impl.declared))
        for name, setting in impl.declared.items():
            typed = f"{setting.kind.__name__} = {shown(setting.default)}"
            summary = " ".join(setting.doc.split("\n\n")[0].split())  # its first paragraph
            click.echo(f"  {name:<{width}} {typed:<14} {summary}".rstrip())
    click.echo("conditions:")
    for c in lib.conditions.values():
        sig = f"{c.name}({', '.join(c.params)})" if c.params else c.name
        mark = "*" if impl and c.name in impl.conditions else " "
        click.echo(f" {mark}{sig:<28} {c.doc}")
    click.echo("actions:")
    for a in lib.actions.values():
        mark = "*" if impl and a.name in impl.actions else " "
        pre = ", ".join(map(str, a.pre)) or "-"
        post = ", ".join(map(str, a.post)) or "-"
        cost = f"  cost {a.cost:g}" if a.cost != 1.0 else ""
        click.echo(f" {mark}{a!s:<28} pre: {pre}  →  post: {post}{cost}")
        if a.doc:
            click.echo(f"  {'':<28} {a.doc}")
    if lib.goals:
        click.echo("goals: " + ", ".join(map(str, lib.goals)))
    if impl and (impl.actions or impl.conditions):
        click.echo("(* = implemented)")
    elif loaded.module_not_imported:
        click.echo("(implementations not loaded: give --with-implementations to mark them)")
    else:
        click.echo(
            "(no implementations registered: the library synthesises and exports, but cannot run yet)"
        )
    echo_diagnostics(loaded.diagnostics)


@library.command("check")
@click.argument("ref")
@click.option(
    "--strict",
    is_flag=True,
    help="Treat warnings (assumed conditions, ambiguous achievers, unreachable actions) as errors.",
)
@click.option("--json", "as_json", is_flag=True, help="Print findings as JSON.")
@with_implementations_option
@handle_spec_errors
def check_cmd(ref: str, strict: bool, as_json: bool, with_implementations: bool) -> None:
    """Check a library: references, parameters, cycles, assumed conditions, ambiguity, reachability.

    A library given by path is checked without importing its implementation module;
    --with-implementations imports it and also checks the names it registers.

    Exit status 1 when errors are found (with --strict: also warnings), 2 when the file cannot be
    read or does not match the library schema.
    """
    with checking_imports(with_implementations):
        loaded = load_library(ref)
    report = check_library(loaded.library, loaded.diagnostics, strict=strict)
    if as_json:
        click.echo(
            json.dumps(
                {
                    "library": loaded.library.name,
                    "ok": report.ok,
                    "findings": [d.to_dict() for d in report.diagnostics],
                },
                indent=2,
            )
        )
    else:
        echo_diagnostics(report.diagnostics)
        c = report.counts()
        click.echo(
            f"{loaded.library.name}: {len(loaded.library.actions)} actions, "
            f"{len(loaded.library.conditions)} conditions — {c['error']} error(s), "
            f"{c['warning']} warning(s), {c['info']} note(s)"
        )
    if errors(report.diagnostics):
        raise ChecksFailed(f"library '{loaded.library.name}' failed its checks")


@library.command("new")
@click.argument("name")
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    default=None,
    callback=output_target("dir"),
    help="Directory to create (default: ./btmission-NAME).",
)
@click.option("--force", is_flag=True, help="Write into an existing non-empty directory.")
@handle_spec_errors
def new_cmd(name: str, output: Path | None, force: bool) -> None:
    """Scaffold a pip-installable plugin package for a new library NAME.

    The package has the entry point, a YAML spec, an implementation module and a passing test;
    after `pip install -e DIR`, `btmission library list` shows it.
    """
    from btmission.cli.common import BadInput
    from btmission.scaffold import ScaffoldError, scaffold_plugin

    target = output or Path(f"btmission-{name.replace('_', '-')}")
    try:
        files = scaffold_plugin(name, target, force=force)
    except ScaffoldError as exc:
        raise BadInput(str(exc)) from None
    for f in files:
        click.echo(f"  created {f}")
    click.echo(f"\nnext: pip install -e {target} && btmission library list && pytest {target}")
