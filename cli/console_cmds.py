"""``btmission task``, ``btmission status`` and ``btmission fleet``: the operator console of a
running mission (``btmission run MISSION --console``) from the command line, for scripts."""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import click

from btmission.cli.common import BadInput, ChecksFailed, FiniteFloat, parse_numbers

F = TypeVar("F", bound=Callable[..., Any])

TOKEN_ENV = "BTMISSION_TOKEN"
TOKEN_HOW = "give it with --token-file FILE, BTMISSION_TOKEN, or ?token= in the URL"
WAIT_STATES = ("added", "assigned", "done")
POLL_S = 0.5
QUIET_NOTES = ("added", "awaiting bids (newly announced)")


def console_options(fn: F) -> F:
    """URL and the token options of every console command."""
    fn = click.option(
        "--insecure",
        is_flag=True,
        help="Accept any TLS certificate (a self-signed one on a test rig).",
    )(fn)
    fn = click.option(
        "--token-file",
        type=click.Path(dir_okay=False, path_type=Path),
        help="Read the run's token from this file (its first line).",
    )(fn)
    fn = click.option(
        "--token",
        envvar=TOKEN_ENV,
        show_envvar=True,
        help="The run's token (printed with its URL; it may also be in URL as ?token=). "
        "Prefer the environment variable or --token-file: a command line is visible to "
        "other users of the machine.",
    )(fn)
    return fn


def read_token_file(path: Path) -> str:
    """The first line of a token file; :class:`BadInput` for a missing, empty or huge one."""
    try:
        with path.open("rb") as fh:
            raw = fh.read(4097)
    except OSError as exc:
        raise BadInput(f"{path}: cannot read the token file: {exc.strerror}") from None
    if len(raw) > 4096:
        raise BadInput(f"{path}: a token file holds one short line (this one is over 4 KB)")
    lines = raw.decode("utf-8", "replace").splitlines()
    token = lines[0].strip() if lines else ""
    if not token:
        raise BadInput(f"{path}: the token file is empty (expected the token on its first line)")
    return token


def _client(url: str, token: str | None, token_file: Path | None, insecure: bool) -> Any:
    from btmission.console.client import ConsoleClient, ConsoleClientError

    if token_file is not None:
        token = read_token_file(token_file)
    try:
        return ConsoleClient(url, token or None, insecure=insecure)
    except ConsoleClientError as exc:
        raise BadInput(str(exc)) from None


def _call(fn: Callable[[], Any]) -> Any:
    """``fn()``; a refusal is :class:`BadInput` (exit 2) with the console's message, no answer
    :class:`ChecksFailed` (exit 1)."""
    from btmission.console.client import ConsoleClientError

    try:
        return fn()
    except ConsoleClientError as exc:
        if exc.status in (0, 429) or exc.status >= 500:
            raise ChecksFailed(str(exc)) from None
        if exc.status in (401, 403) and "token" in str(exc):
            raise BadInput(f"{exc}: {TOKEN_HOW}") from None
        raise BadInput(str(exc)) from None


def _say(answer: Any) -> None:
    click.echo(answer.get("message", json.dumps(answer)) if isinstance(answer, dict) else answer)


# ---------------------------------------------------------------------------- task
@click.group("task")
def task_group() -> None:
    """Add, cancel or reprioritise a task of a running mission.

    URL is the console's, as `btmission run MISSION --console` printed it (the token may be in
    it: http://127.0.0.1:8470/?token=...). A task is checked as a task of the mission file is,
    and its positions against the map; a refusal says why and exits 2.
    """


def _field_value(text: str, name: str = "") -> Any:
    """``x,y,z`` → a position, a number → a number, anything else → a place name (a value
    with commas must be a position)."""
    nums = parse_numbers(text, 3)
    if nums is not None:
        return list(nums)
    if "," in text:
        raise BadInput(f"--field {name}={text}: expected a position X,Y,Z (three finite numbers)")
    try:
        v = float(text)
    except ValueError:
        return text.strip()
    return v if math.isfinite(v) else text


@task_group.command("add")
@click.argument("url")
@click.option("--type", "task_type", required=True, help="The task type (the mission's).")
@click.option(
    "--at",
    "at_point",
    metavar="X,Y,Z",
    help="Where: the type's first position field (e.g. location) in metres, map frame.",
)
@click.option(
    "--field",
    "-f",
    "fields",
    multiple=True,
    metavar="NAME=VALUE",
    help="A field of the type: a position x,y,z, a number or a place name (repeat: "
    "-f pickup=10,5,0 -f dropoff=crusher).",
)
@click.option("--id", "task_id", help="The task's id (default: the next free one, e.g. T8).")
@click.option(
    "--priority",
    help="A number > 0, or low / normal / high / urgent (0.5, 1, 2, 4 × the type's priority).",
)
@click.option(
    "--wait",
    type=click.Choice(WAIT_STATES),
    default="added",
    show_default=True,
    help="Return once the task is added, assigned to an agent, or done (printing each change).",
)
@click.option(
    "--timeout",
    type=FiniteFloat(min=0.1, max=86_400),
    default=120.0,
    show_default=True,
    help="Give up waiting after this many seconds (wall clock).",
)
@console_options
def task_add(
    url: str,
    task_type: str,
    at_point: str | None,
    fields: tuple[str, ...],
    task_id: str | None,
    priority: str | None,
    wait: str,
    timeout: float,
    token: str | None,
    token_file: Path | None,
    insecure: bool,
) -> None:
    """Add a task to the running mission at URL.

    \b
    Example:
      btmission task add http://127.0.0.1:8470/ --type inspect --at 60,9.5,2 --priority high
      btmission task add URL --type pick_and_deliver -f pickup=10,5,0.5 -f dropoff=30,8,0.5

    Prints "T8 added at 116.1 s" (with --wait assigned: "T8 assigned to R2 at 117.2 s").
    Exit status: 0 added (assigned, done), 1 it became unreachable or failed, the wait timed
    out, or the console did not answer, 2 refused (the message says why: a field, a point
    inside rock, the token).
    """
    client = _client(url, token, token_file, insecure)
    body: dict[str, Any] = {"type": task_type}
    for item in fields:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise BadInput(f"--field '{item}': expected NAME=VALUE (e.g. location=60,9.5,2)")
        body[name.strip()] = _field_value(value, name.strip())
    if at_point is not None:
        point = parse_numbers(at_point, 3)
        if point is None:
            raise BadInput(f"--at '{at_point}': expected X,Y,Z (three finite numbers)")
        types = _call(client.console).get("task_types", {})
        positions = types.get(task_type, {}).get("positions") or []
        free = [p for p in positions if p not in body]
        if task_type in types and not free:
            given = ", ".join(f"-f {p}" for p in positions if p in body)
            raise BadInput(
                f"--at fills the first position field of '{task_type}', but {given} gave it "
                "already: give one of them"
                if given
                else f"--at: task type '{task_type}' has no position field (its fields: "
                f"{', '.join(types[task_type].get('fields', [])) or 'none'}): use -f NAME=VALUE"
            )
        body[free[0] if free else "location"] = list(point)
    if task_id:
        body["id"] = task_id
    if priority is not None:
        body["priority"] = _field_value(priority) if priority[:1].isdigit() else priority
    answer = _call(lambda: client.add_task(body))
    _say(answer)
    if wait != "added":
        _wait_for(client, str(answer.get("task")), wait, timeout)


def _wait_for(client: Any, task: str, until: str, timeout: float) -> None:
    """Poll the status until ``task`` is assigned (or done), printing each change of its
    history once (the status carries its latest changes, so none is missed between polls)."""
    deadline = time.monotonic() + timeout
    from btmission.console.client import ConsoleClientError

    printed: set[tuple[float, str, str | None]] = set()
    while True:
        try:
            status = client.status()
        except ConsoleClientError as exc:
            if exc.status == 0:  # it answered before: the run ended or was stopped meanwhile
                raise ChecksFailed(
                    f"the console went away before {task} was {until}: the run ended or was "
                    "stopped (its report says how)"
                ) from None
            raise ChecksFailed(str(exc)) from None
        row = next((t for t in status.get("tasks", []) if t.get("id") == task), None)
        if row is not None:
            for t, state, agent, reason in row.get("history", []):
                if (t, state, agent) in printed:
                    continue
                printed.add((t, state, agent))
                if not (state == "open" and reason in QUIET_NOTES):  # just added: no news
                    click.echo(_change(task, t, state, agent, reason))
            state = row.get("state")
            if state in ("unreachable", "failed", "cancelled"):
                raise ChecksFailed(f"{task} {state}: {row.get('note') or 'no reason given'}")
            if state == "done" or (until == "assigned" and state in ("assigned", "committed")):
                return
        if not status.get("running", True):
            raise ChecksFailed(f"the run ended ({status.get('ended')}) before {task} was {until}")
        if time.monotonic() > deadline:
            raise ChecksFailed(f"{task} was not {until} within {timeout:g} s (it goes on)")
        time.sleep(POLL_S)


def _change(task: str, t: float, state: str, agent: str | None, reason: str) -> str:
    """One line for one change of a task's state."""
    if state in ("assigned", "committed"):
        return f"{task} {state} to {agent} at {t:.1f} s"
    if state == "done":
        return f"{task} done by {agent} at {t:.1f} s"
    return f"{task} {state} at {t:.1f} s" + (f": {reason}" if reason else "")


@task_group.command("cancel")
@click.argument("url")
@click.argument("task")
@console_options
def task_cancel(
    url: str, task: str, token: str | None, token_file: Path | None, insecure: bool
) -> None:
    """Cancel TASK: it leaves the pool (state cancelled) and its agent stops it.

    \b
    Example:
      btmission task cancel http://127.0.0.1:8470/ T8

    Exit status: 0 done, 1 the console did not answer (or too many requests), 2 refused (the message says why).
    """
    client = _client(url, token, token_file, insecure)
    _say(_call(lambda: client.cancel_task(task)))


@task_group.command("priority")
@click.argument("url")
@click.argument("task")
@click.argument("priority")
@console_options
def task_priority(
    url: str,
    task: str,
    priority: str,
    token: str | None,
    token_file: Path | None,
    insecure: bool,
) -> None:
    """Change TASK's priority: a number > 0, or low / normal / high / urgent (0.5, 1, 2, 4 ×
    its type's priority). The task is announced again with it.

    \b
    Example:
      btmission task priority http://127.0.0.1:8470/ T3 urgent

    Exit status: 0 done, 1 the console did not answer (or too many requests), 2 refused (the message says why).
    """
    client = _client(url, token, token_file, insecure)
    value: float | str = _field_value(priority) if priority[:1].isdigit() else priority
    _say(_call(lambda: client.set_priority(task, value)))


# ---------------------------------------------------------------------------- status
@click.command("status")
@click.argument("url")
@click.option("--json", "as_json", is_flag=True, help="Print the status as JSON.")
@console_options
def status_cmd(
    url: str,
    as_json: bool,
    token: str | None,
    token_file: Path | None,
    insecure: bool,
) -> None:
    """Show the agents and tasks of the running mission at URL (a table; --json for scripts).

    Needs no token on loopback (it changes nothing); works on a --view run too.

    \b
    Example:
      btmission status http://127.0.0.1:8470/

    Exit status: 0 shown, 1 the console did not answer, 2 refused.
    """
    client = _client(url, token, token_file, insecure)
    status = _call(client.status)
    if as_json:
        click.echo(json.dumps(status, indent=2))
        return
    click.echo(format_status(status))


def format_status(status: dict[str, Any]) -> str:
    """The status as two tables (agents, tasks) under a line saying when and how it runs."""
    from btmission.runtime.report import table_lines

    state = "running" if status.get("running") else f"ended ({status.get('ended')})"
    paused = (status.get("allocation") or {}).get("paused")
    lines = [
        f"t = {status.get('t', 0):.1f} s, {state}; allocation {'PAUSED' if paused else 'running'}",
        "",
    ]
    agents = []
    for a in status.get("agents", []):
        flags = [
            f for f, on in (
                ("lost", not a.get("alive")), ("link down", not a.get("link_up")),
                ("recalled", a.get("recalled")), ("excluded", a.get("excluded")),
            ) if on
        ]  # fmt: skip
        p = a.get("p") or []
        agents.append(tuple(str(c) for c in (
            a.get("id"), a.get("task") or "-", a.get("action") or "-", a.get("mode"),
            "[" + ", ".join(f"{v:.1f}" for v in p) + "]", ", ".join(flags) or "ok",
        )))  # fmt: skip
    lines += table_lines(("agent", "task", "action", "mode", "position", "state"), agents)
    lines.append("")
    tasks = [
        tuple(str(c) for c in (
            t.get("id"), t.get("type"), t.get("state"), t.get("agent") or "-",
            f"{t.get('priority', 0):g}", f"{t.get('added_s', 0):.1f}", t.get("note") or "",
        ))
        for t in status.get("tasks", [])
    ]  # fmt: skip
    header = ("task", "type", "state", "agent", "priority", "added (s)", "note")
    lines += table_lines(header, tasks)
    return "\n".join(lines)


# ---------------------------------------------------------------------------- fleet
@click.group("fleet")
def fleet_group() -> None:
    """Recall, exclude or include an agent, cut its link (simulator drills), pause or resume
    allocation, or stop a running mission (its console at URL; see btmission task).

    Exit status: 0 done, 1 the console did not answer (or too many requests), 2 refused (the message says why). Doing again what is done already (a second pause) is not an error: the answer says
    "(it was already)".
    """


def _agent_command(name: str, action: str, doc: str) -> None:
    @fleet_group.command(name, help=doc)
    @click.argument("url")
    @click.argument("agent")
    @console_options
    def cmd(
        url: str, agent: str, token: str | None, token_file: Path | None, insecure: bool
    ) -> None:
        client = _client(url, token, token_file, insecure)
        _say(_call(lambda: client.agent(agent, action)))


_agent_command(
    "recall",
    "recall",
    "AGENT gives up its task, bids no more and runs its default behaviour now (e.g. return "
    "home and land); `fleet include` brings it back.\n\n\b\nExample:\n"
    "  btmission fleet recall http://127.0.0.1:8470/ R2",
)
_agent_command(
    "exclude",
    "exclude",
    "Take AGENT out of the auction: it keeps the task it holds and wins nothing else.",
)
_agent_command("include", "include", "Put AGENT (excluded or recalled) back into the auction.")


@fleet_group.command("link")
@click.argument("url")
@click.argument("agent")
@click.argument("state", type=click.Choice(["down", "up"]))
@console_options
def fleet_link(
    url: str,
    agent: str,
    state: str,
    token: str | None,
    token_file: Path | None,
    insecure: bool,
) -> None:
    """Cut (down) or restore (up) AGENT's link to the coordinator, for drills: simulated
    vehicles only. The agent keeps executing its task meanwhile (seed 000 §V-C).

    \b
    Example:
      btmission fleet link http://127.0.0.1:8470/ R1 down
    """
    client = _client(url, token, token_file, insecure)
    _say(_call(lambda: client.agent(agent, "link", {"up": state == "up"})))


@fleet_group.command("pause")
@click.argument("url")
@console_options
def fleet_pause(url: str, token: str | None, token_file: Path | None, insecure: bool) -> None:
    """Pause allocation: every agent keeps the task it holds, nothing else is assigned."""
    client = _client(url, token, token_file, insecure)
    _say(_call(lambda: client.set_allocation(True)))


@fleet_group.command("resume")
@click.argument("url")
@console_options
def fleet_resume(url: str, token: str | None, token_file: Path | None, insecure: bool) -> None:
    """Resume allocation."""
    client = _client(url, token, token_file, insecure)
    _say(_call(lambda: client.set_allocation(False)))


@fleet_group.command("stop")
@click.argument("url")
@click.option("--reason", default="", help="Logged with the command.")
@console_options
def fleet_stop(
    url: str, reason: str, token: str | None, token_file: Path | None, insecure: bool
) -> None:
    """End the run after the current step: its log and report are complete, as after Ctrl-C
    on its terminal; the run's own exit status is then 0 if every task is done, else 1 (not
    Ctrl-C's 130). --reason is logged, with who stopped it."""
    client = _client(url, token, token_file, insecure)
    _say(_call(lambda: client.stop(reason)))


def token_for_run(token_file: Path | None) -> str | None:
    """The token a run's console uses: --token-file, else BTMISSION_TOKEN, else None (a new one
    is made)."""
    if token_file is not None:
        return read_token_file(token_file)
    return os.environ.get(TOKEN_ENV) or None
