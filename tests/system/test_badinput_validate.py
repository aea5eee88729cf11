"""Issue #12 §2: ``validate`` accepts exactly what ``run`` can run.

Bad numbers (NaN, ±inf, 1e400, ``true``), runtime settings, cost expressions and backends are
refused by ``validate`` and ``run`` alike, with file:line:col and the item; CLI number options
refuse non-finite values and negative seeds. The bad-input corpus in ``tests/data/badinput``
(one file per fault, named for it; its second line says what is expected) drives most of it.
"""

from __future__ import annotations

import re
from pathlib import Path

import click
import pytest
from click.testing import CliRunner, Result

from btmission.cli.common import FiniteFloat
from btmission.cli.main import cli

ROOT = Path(__file__).resolve().parents[2]
CORPUS = ROOT / "tests" / "data" / "badinput"
EXPECT = re.compile(r"^# expect: exit (?P<code>\d)(?: line (?P<line>\d+))?(?:: (?P<message>.*))?$")
FAST_RUN = ["--until", "1", "--no-png", "--quiet", "--controller", "track"]


@pytest.fixture(scope="module")
def runner() -> CliRunner:
    return CliRunner()


def invoke(runner: CliRunner, *args: str) -> Result:
    result = runner.invoke(cli, list(args))
    assert "Traceback" not in result.output, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit), result.output
    return result


def refused_by_validate_and_run(runner: CliRunner, path: Path, logs: Path, *wanted: str) -> None:
    """``validate`` and ``run`` both exit 2 naming every ``wanted`` text; run writes no log."""
    for args in (["validate", str(path)], ["run", str(path), "--log", str(logs), *FAST_RUN]):
        result = invoke(runner, *args)
        assert result.exit_code == 2, (args, result.output)
        for text in wanted:
            assert text in result.output, (args, text, result.output)
    assert not list(logs.glob("*.jsonl"))


def corpus(prefix: str = "") -> list[Path]:
    return sorted(p for p in CORPUS.glob("*.yaml") if p.name.startswith(prefix))


def expectation(path: Path) -> tuple[int, int | None, str | None, str]:
    """(exit status, line, message, kind) from the file's two header lines."""
    head = path.read_text().splitlines()[:2]
    kind = head[0].removeprefix("# ").split(";")[0]
    m = EXPECT.match(head[1])
    assert m, f"{path}: second line must be '# expect: exit N [line L][: message]'"
    line = int(m["line"]) if m["line"] else None
    return int(m["code"]), line, m["message"], kind


def is_mission(path: Path) -> bool:
    return any(t.startswith("mission:") for t in path.read_text().splitlines())


# ------------------------------------------------------------------------------ the corpus
@pytest.mark.parametrize("path", corpus(), ids=lambda p: p.stem)
def test_corpus_file_gets_its_expected_answer(runner: CliRunner, path: Path) -> None:
    code, line, message, kind = expectation(path)
    rel = str(path.relative_to(ROOT))
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ROOT)
        command = {"mission": ["validate"], "library": ["library", "check"]}.get(
            kind, ["dispatch", "map"]
        )
        result = invoke(runner, *command, rel)
    assert result.exit_code == code, result.output
    if line is not None:
        assert f"{rel}:{line}:" in result.output, result.output
    if message is not None:
        assert message in result.output, result.output
    if code == 2:
        assert "nothing was run" in result.output or "problem(s)" in result.output


def test_corpus_names_say_what_is_wrong() -> None:
    files = corpus()
    assert len(files) >= 40
    for p in files:
        first = p.read_text().splitlines()[0]
        assert first.startswith(tuple(f"# {k}; wrong: " for k in ("mission", "library", "topomap")))
        assert p.stem.startswith("ok_") == (expectation(p)[0] == 0), p


# ------------------------------------------------------------------------------ runtime: section
class TestRuntimeSettings:
    def test_unknown_setting_has_did_you_mean_in_validate_and_run(
        self, runner: CliRunner, tmp_path: Path
    ) -> None:
        path = CORPUS / "setting_unknown_name.yaml"
        want = (
            f"{path}:15:14: runtime.settings.sped_m_s: unknown setting 'sped_m_s' "
            "(did you mean 'speed_m_s'?); known: "
        )
        refused_by_validate_and_run(runner, path, tmp_path, want)

    @pytest.mark.parametrize(
        "name, message",
        [
            ("setting_speed_string", "runtime.settings.speed_m_s: expected a number (got 'fast')"),
            ("setting_speed_bool", "runtime.settings.speed_m_s: expected a number (got true)"),
            ("setting_speed_zero", "runtime.settings.speed_m_s: expected a number > 0 (got 0)"),
            ("setting_speed_nan", "runtime.settings.speed_m_s: expected a finite number (got nan)"),
            ("setting_replans_fraction", "replans: expected an integer (got 2.5)"),
            ("setting_library_time_negative", "pick_time_s: expected a number ≥ 0 (got -2)"),
        ],
    )
    def test_bad_setting_values_are_refused_by_run_too(
        self, runner: CliRunner, tmp_path: Path, name: str, message: str
    ) -> None:
        path = CORPUS / f"{name}.yaml"
        result = invoke(runner, "run", str(path), "--log", str(tmp_path), *FAST_RUN)
        assert result.exit_code == 2, result.output
        assert f"{path}:15:" in result.output and message in result.output

    def test_runtime_ranges_and_keys(self, runner: CliRunner) -> None:
        for name, message in (
            ("mission_max_duration_zero", "runtime.max_duration_s: Input should be greater than 0"),
            ("mission_runtime_unknown_key", "runtime.tick_rate: unknown key 'tick_rate'"),
            ("mission_path_fields_too_small", "runtime.path_fields_mb: Input should be greater"),
            ("mission_participation_over_1", "coordination.participation: Input should be less"),
        ):
            result = invoke(runner, "validate", str(CORPUS / f"{name}.yaml"))
            assert result.exit_code == 2 and message in result.output, result.output

    def test_library_settings_use_their_declared_defaults(self) -> None:
        from btmission.runtime.runcheck import setting_problem

        assert setting_problem("dispatch_generations", 2.5, 200) == (
            "expected an integer (got 2.5)"
        )
        assert setting_problem("dispatch_generations", 0, 200) == "expected an integer ≥ 1 (got 0)"
        assert setting_problem("reloc_database", 3, "") == "expected a string (got 3)"
        assert setting_problem("reloc_database", "db.npz", "") is None
        assert setting_problem("custom_flag", "yes", True) == "expected true or false (got 'yes')"
        assert setting_problem("custom_gain", -3.0, 1.0) is None  # no unit: any finite number
        assert setting_problem("custom_wait_s", -3.0, 1.0) == "expected a number ≥ 0 (got -3.0)"


class TestLibraryChecks:
    """What a library's services or setup hooks refuse at run time, validate finds first."""

    @pytest.mark.parametrize(
        "name, line, message",
        [
            ("haulage_without_topomap", 6, "world.topomap: library 'haulage' needs a topological"),
            ("haulage_start_off_road", 11, "agents.H2.start: agent 'H2' starts 220 m from"),
            ("haulage_two_trucks_one_node", 11, "both start at node L1n: one truck per node"),
            ("reloc_database_missing", 14, "no_such_places.npz: no such file"),
        ],
    )
    def test_validate_and_run_refuse_alike(
        self, runner: CliRunner, tmp_path: Path, name: str, line: int, message: str
    ) -> None:
        path = CORPUS / f"{name}.yaml"
        refused_by_validate_and_run(runner, path, tmp_path, f"{path}:{line}:", message)


# ------------------------------------------------------------------------------ non-finite numbers
class TestNonFinite:
    @pytest.mark.parametrize(
        "text, item, shown",
        [
            (".nan", "agents[0].start[2]", "nan"),
            ("1e400", "agents[0].start[2]", "1e400"),
            ("-.inf", "agents[0].start[2]", "-inf"),
            ("true", "agents[0].start[2]", "true"),
        ],
    )
    def test_start_coordinates(
        self, runner: CliRunner, tmp_path: Path, text: str, item: str, shown: str
    ) -> None:
        base = (CORPUS / "ok_cost_number.yaml").read_text()
        path = tmp_path / "m.yaml"
        path.write_text(base.replace("start: [2, 2, 0]", f"start: [2, 2, {text}]"))
        result = invoke(runner, "validate", str(path))
        assert result.exit_code == 2, result.output
        kind = "a number" if text == "true" else "a finite number"
        assert f"{path}:8:" in result.output
        assert f"{item}: expected {kind} (got {shown})" in result.output

    def test_library_costs(self, runner: CliRunner) -> None:
        for name, message in (
            ("library_cost_inf", "actions.go.cost: expected a finite number (got inf)"),
            ("library_cost_1e400", "actions.go.cost: expected a finite number (got 1e400)"),
            ("library_cost_true", "actions.go.cost: expected a number (got true)"),
        ):
            path = CORPUS / f"{name}.yaml"
            result = invoke(runner, "library", "check", str(path))
            assert result.exit_code == 2 and f"{path}:8:" in result.output, result.output
            assert message in result.output

    def test_a_mission_using_a_bad_library_names_the_library_line(self, runner: CliRunner) -> None:
        result = invoke(runner, "validate", str(CORPUS / "library_cost_inf_used.yaml"))
        assert result.exit_code == 2
        assert f"{CORPUS / 'library_cost_inf.yaml'}:8:" in result.output
        assert "actions.go.cost: expected a finite number (got inf)" in result.output

    def test_task_fields_and_times(self, runner: CliRunner) -> None:
        for name, message in (
            ("mission_task_location_inf", "coordinates must be finite numbers"),
            ("mission_task_at_1e400", "tasks[0].at: expected a finite number (got 1e400)"),
            ("mission_task_priority_bool", "tasks[0].priority: expected a number (got true)"),
            ("mission_priority_scale_inf", "priority_scale: expected a finite number (got inf)"),
        ):
            path = CORPUS / f"{name}.yaml"
            result = invoke(runner, "validate", str(path))
            assert result.exit_code == 2 and message in result.output, result.output

    def test_finite_float_type(self) -> None:
        from pydantic import BaseModel, ValidationError

        from btmission.spec.common import FiniteFloat as Finite

        class M(BaseModel):
            x: Finite

        assert M(x="1e5").x == 1e5  # YAML 1.1 reads 1e5 as a string: still a number
        for bad in (float("nan"), float("inf"), "1e400", True):
            with pytest.raises(ValidationError):
                M(x=bad)


# ------------------------------------------------------------------------------ CLI numbers
def _commands(
    group: click.Group, prefix: tuple[str, ...] = ()
) -> list[tuple[tuple[str, ...], click.Command]]:
    out: list[tuple[tuple[str, ...], click.Command]] = []
    for name, cmd in sorted(group.commands.items()):
        if isinstance(cmd, click.Group):
            out.extend(_commands(cmd, (*prefix, name)))
        else:
            out.append(((*prefix, name), cmd))
    return out


def _float_options() -> list[tuple[tuple[str, ...], str]]:
    found = []
    for path, cmd in _commands(cli):  # type: ignore[arg-type]
        for p in cmd.params:
            if isinstance(p, click.Option) and isinstance(
                p.type, (click.FloatRange, type(click.FLOAT))
            ):
                found.append((path, p.opts[-1] if p.opts[-1].startswith("--") else p.opts[0]))
    return found


class TestCliNumbers:
    def test_every_float_option_is_finite_and_every_seed_non_negative(self) -> None:
        floats = seeds = 0
        for path, cmd in _commands(cli):  # type: ignore[arg-type]
            for p in cmd.params:
                if isinstance(p.type, (click.FloatRange, type(click.FLOAT))):
                    assert isinstance(p.type, FiniteFloat), (path, p.name)
                    floats += 1
                if p.name == "seed":
                    assert isinstance(p.type, click.IntRange) and p.type.min == 0, (path, p.name)
                    seeds += 1
        assert floats >= 15 and seeds >= 5

    @pytest.mark.parametrize("command, option", _float_options(), ids=lambda v: str(v))
    def test_nan_is_refused(self, runner: CliRunner, command: tuple[str, ...], option: str) -> None:
        cmd = cli
        for name in command:
            cmd = cmd.commands[name]  # type: ignore[attr-defined]
        param = next(p for p in cmd.params if option in p.opts)
        value = ["nan"] * (param.nargs if param.nargs > 1 else 1)
        result = invoke(runner, *command, option, *value)
        assert result.exit_code == 2, result.output
        assert "Invalid value for " in result.output and f"'{option}'" in result.output
        assert "'nan' is not a finite number" in result.output

    def test_run_until_nan_inf_and_seed_minus_one(self, runner: CliRunner, tmp_path: Path) -> None:
        mission = str(CORPUS / "ok_cost_number.yaml")
        for args, message in (
            (["--until", "nan"], "Invalid value for '--until': 'nan' is not a finite number"),
            (["--until", "inf"], "Invalid value for '--until': 'inf' is not a finite number"),
            (["--until", "0"], "Invalid value for '--until': 0.0 is not in the range x>0"),
            (["--seed", "-1"], "Invalid value for '--seed': -1 is not in the range x>=0"),
        ):
            result = invoke(runner, "run", mission, "--log", str(tmp_path), *args)
            assert result.exit_code == 2 and message in result.output, (args, result.output)
        assert not list(tmp_path.glob("*.jsonl"))

    def test_points_with_nan_are_refused(self, runner: CliRunner) -> None:
        result = invoke(runner, "plan", str(CORPUS / "ok_cost_number.yaml"), "--from", "1,1,nan",
                        "--to", "2,2,0")  # fmt: skip
        assert result.exit_code == 2
        assert "expected X,Y,Z in metres (three finite numbers), got '1,1,nan'" in result.output


# ------------------------------------------------------------------------------ cost expressions
class TestCostExpressions:
    @pytest.mark.parametrize(
        "name, message",
        [
            ("cost_division_by_zero", "division by zero in 'path_cost(location) / 0'"),
            ("cost_division_by_path_cost", "when every path cost is 0 (task 'T1')"),
            ("cost_overflow", "overflow (the value is inf) in '1e308 * 10 + path_cost(location)'"),
            ("cost_literal_too_large", "is too large (not finite)"),
            ("cost_negative", "'-1' is -1; bids must be ≥ 0 (task 'T1')"),
            ("cost_position_times_two", "task field 'location' is not a number"),
        ],
    )
    def test_reported_at_the_task_types_cost_by_validate_and_run(
        self, runner: CliRunner, tmp_path: Path, name: str, message: str
    ) -> None:
        path = CORPUS / f"{name}.yaml"
        refused_by_validate_and_run(
            runner, path, tmp_path, f"{path}:12:", "task_types.visit.cost: ", message
        )

    def test_guarded_evaluator(self) -> None:
        import math

        from btmission.spec.costexpr import CostExprError, parse_cost

        expr = parse_cost("path_cost(a) / distance(b)")
        with pytest.raises(CostExprError, match="division by zero in 'path_cost"):
            expr.evaluate(lambda name, args: 0.0, {"a": [0, 0, 0], "b": [0, 0, 0]})
        assert expr.evaluate(lambda name, args: 2.0, {"a": 1, "b": 1}) == 1.0
        # no path (an infinite path cost) stays infinite: the bidder reads it as unreachable
        unreachable = parse_cost("path_cost(a) + 1")
        assert math.isinf(unreachable.evaluate(lambda name, args: math.inf, {"a": [0, 0, 0]}))
        with pytest.raises(CostExprError, match="overflow"):
            parse_cost("w * w").evaluate(lambda name, args: 0.0, {"w": 1e200})


# ------------------------------------------------------------------------------ backends
class TestBackend:
    def test_trees_of_a_mavlink_mission_still_build(self, runner: CliRunner) -> None:
        path = CORPUS.parent / "mavlink_ground.yaml"
        result = invoke(runner, "mission", "tree", str(path), "--agent", "G1")
        assert result.exit_code == 0 and "Fallback: mission(G1)" in result.output, result.output

    def test_an_unknown_scheme_is_refused_by_validate_and_run(
        self, runner: CliRunner, tmp_path: Path
    ) -> None:
        path = CORPUS / "backend_unknown.yaml"
        want = (
            f"{path}:8:58: agents[0].backend: backend 'gazebo': no vehicle provider for scheme "
            "'gazebo' is installed; installed: 'sim', 'fake', 'mavlink' (entry-point group 'btmission.providers')"
        )
        refused_by_validate_and_run(runner, path, tmp_path, want)

    def test_the_url_grammar_is_still_checked(self, runner: CliRunner, tmp_path: Path) -> None:
        text = (CORPUS / "backend_unknown.yaml").read_text()
        for bad, want in (
            ("Gazebo sim", "expected 'sim' or a vehicle provider's URL <scheme>://<address>"),
            (
                "mavlink://127.0.0.1:14540",
                "MAVLink URL 'mavlink://127.0.0.1:14540': say the transport in the scheme",
            ),
        ):
            path = tmp_path / "m.yaml"
            path.write_text(text.replace("backend: gazebo", f"backend: '{bad}'"))
            result = invoke(runner, "validate", str(path))
            assert result.exit_code == 2
            assert f"{path}:8:58: agents[0].backend: {want}" in result.output, result.output


# ------------------------------------------------------------------------------ docs agree
class TestDocsAgree:
    def test_an_unquoted_number_is_a_cost(self, runner: CliRunner) -> None:
        doc = (ROOT / "docs" / "mission-format.md").read_text()
        assert '`cost: 1` and `cost: "1"` mean the same' in doc
        assert "It must be a string" not in doc and "Quote a cost that is a bare number" not in doc
        result = invoke(runner, "validate", str(CORPUS / "ok_cost_number.yaml"))
        assert result.exit_code == 0 and "mission 'badinput' OK" in result.output

    def test_a_bare_action_is_an_action_without_keys(self, runner: CliRunner) -> None:
        doc = (ROOT / "docs" / "library-format.md").read_text()
        assert "A bare action, `beep:` with nothing after it, is the same as `beep: {}`" in doc
        assert "a bare `beep:` is a schema error" not in doc
        path = CORPUS / "ok_library_bare_action.yaml"
        result = invoke(runner, "library", "check", str(path))
        assert result.exit_code == 0, result.output
        assert (
            f"{path}:8:3: warning: actions.start_up: action 'start_up' has no postconditions"
            in (result.output)
        )

    def test_mavlink_is_documented_as_flown(self) -> None:
        doc = (ROOT / "docs" / "mission-format.md").read_text()
        assert "no vehicle provider for scheme 'mavlink' is installed" not in doc
        assert "[MAVLink vehicles](mavlink.md)" in doc


# ------------------------------------------------------------------------------ validate ⇒ run
def _missions(*dirs: Path) -> list[Path]:
    return sorted(p for d in dirs for p in d.glob("*.yaml") if is_mission(p))


def check_validate_implies_run(runner: CliRunner, path: Path, logs: Path) -> None:
    """``validate`` exit 0 ⇒ ``run --until 1`` exits 0 or 1 without a traceback (an abstract
    library, documented as synthesis-only, is refused by run with a clear message)."""
    checked = invoke(runner, "validate", str(path))
    if checked.exit_code != 0:
        assert checked.exit_code in (1, 2), checked.output
        return
    text = path.read_text()
    if "mavlink: {time_scale: 4}" in text:  # a shipped MAVLink mission: no vehicle answers here
        path = logs / path.name  # (its map is generated: the copy builds the same world)
        path.write_text(text.replace("{time_scale: 4}", "{time_scale: 4, connect_timeout_s: 1}"))
    result = invoke(runner, "run", str(path), "--log", str(logs), *FAST_RUN)
    if result.exit_code == 2 and "cannot run" in result.output:
        assert "it is abstract" in result.output, result.output
        return
    if result.exit_code == 2 and "may be real" in result.output:  # vehicles to confirm first
        assert "add --yes to fly them without asking" in result.output, result.output
        return
    assert result.exit_code in (0, 1), (path, result.output)


HEAVY = {"reloc_mine.yaml"}
"""Missions whose world takes seconds to build (a place database): with the shipped ones."""
FAST_MISSIONS = [p for p in _missions(CORPUS, ROOT / "docs" / "examples") if p.name not in HEAVY]
SLOW_MISSIONS = _missions(ROOT / "missions") + [ROOT / "docs" / "examples" / n for n in HEAVY]


@pytest.mark.parametrize("path", FAST_MISSIONS, ids=lambda p: p.stem)
def test_validate_implies_run(runner: CliRunner, tmp_path: Path, path: Path) -> None:
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ROOT)
        check_validate_implies_run(runner, path, tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("path", SLOW_MISSIONS, ids=lambda p: p.stem)
def test_validate_implies_run_for_the_shipped_missions(
    runner: CliRunner, tmp_path: Path, path: Path
) -> None:
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(ROOT)
        check_validate_implies_run(runner, path, tmp_path)


def test_the_property_covers_the_corpus_the_docs_and_the_missions() -> None:
    names = {p.name for p in FAST_MISSIONS + SLOW_MISSIONS}
    assert {"ok_abstract_library.yaml", "rail_mission.yaml", "bad_settings.yaml"} <= names
    assert {"mine_inspection.yaml", "warehouse.yaml", "mine_haulage.yaml"} <= names
