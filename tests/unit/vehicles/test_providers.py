"""Vehicle providers: the ``btmission.providers`` registry, the checks on agents' ``backend:``, how
a run gets its vehicles, and the interface module's independence from the algorithms."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import ClassVar

import pytest
from click.testing import CliRunner

from btmission.backends.fake import fake_provider
from btmission.backends.sim_provider import SimProvider, sim_provider
from btmission.cli.main import cli
from btmission.missions import load_mission_text
from btmission.runtime.runner import MissionRun
from btmission.spec.mission import Mission
from btmission.spec.vehicleref import SIM, VehicleRef
from btmission.types import Vec3
from btmission.vehicles import provider as registry
from btmission.vehicles.base import VehicleKind
from btmission.vehicles.provider import (
    ENTRY_POINT_GROUP,
    AttachOptions,
    AttachRequest,
    ProviderError,
    ProviderPlugin,
    Vehicle,
    VehicleEvent,
    VehicleUnavailable,
    installed_providers,
    provider_factory,
)
from btmission.world.voxel import VoxelMap

MISSION = """\
mission: fleet
version: 1
world:
  map: {{generate: empty, size: [20, 20, 4]}}
agents:
  - {{id: G1, library: ground, start: [2, 2, 0], backend: {first}}}
  - {{id: G2, library: ground, start: [4, 2, 0], backend: {second}}}
tasks:
  - {{id: T1, type: visit, location: [6, 2, 0]}}
task_types:
  visit: {{goal: at_goal(location), cost: path_cost(location)}}
runtime: {{controller: track}}
"""


def write(tmp_path: Path, first: str, second: str) -> Path:
    path = tmp_path / "m.yaml"
    path.write_text(MISSION.format(first=first, second=second))
    return path


def validate(path: Path) -> tuple[int, str]:
    result = CliRunner().invoke(cli, ["validate", str(path)])
    assert "Traceback" not in result.output, result.output
    return result.exit_code, result.output


# ------------------------------------------------------------------------------ a test provider
class Recording(SimProvider):
    """The simulator under another scheme, recording what the run asks of it."""

    made: ClassVar[list[Recording]] = []

    def __init__(self, inner: SimProvider) -> None:
        super().__init__(inner.sim)
        self.attached: list[tuple[str, VehicleKind, Vec3, str, AttachOptions]] = []
        self.steps: list[float] = []
        self.closed = False
        self.phases: list[str] = []
        """The phases called before the first step, in order (attach: once per agent)."""
        Recording.made.append(self)

    def warm_up(self) -> None:
        self.phases.append("warm_up")
        super().warm_up()

    def prepare(self, vehicles: Sequence[VehicleRef]) -> None:
        self.phases.append("prepare")

    def start(self) -> None:
        self.phases.append("start")

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        self.attached.append((agent_id, kind, start, ref.url, options))
        self.phases.append("attach")
        return super().attach(agent_id, kind, start, ref, options)

    def step(self, dt: float) -> list[VehicleEvent]:
        self.steps.append(dt)
        return super().step(dt)

    def close(self) -> None:
        self.closed = True


def recording_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> Recording:
    return Recording(sim_provider(mission, voxel_map, seed))


@pytest.fixture
def replay_installed(monkeypatch: pytest.MonkeyPatch) -> None:
    """A second provider, scheme ``replay``, registered like an installed plugin's."""
    real = registry.installed_providers

    def installed() -> dict[str, metadata.EntryPoint]:
        out = real()
        out["replay"] = metadata.EntryPoint(
            "replay", f"{__name__}:recording_provider", ENTRY_POINT_GROUP
        )
        return out

    monkeypatch.setattr(registry, "installed_providers", installed)
    Recording.made.clear()


# ------------------------------------------------------------------------------ the registry
def test_the_sim_provider_is_an_installed_entry_point() -> None:
    [ep] = {ep.value for ep in metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name == "sim"}
    assert ep == "btmission.backends.sim_provider:sim_provider"
    assert installed_providers()["sim"].value == ep
    assert provider_factory("sim") is sim_provider


def test_the_fake_provider_is_declared_next_to_sim() -> None:
    toml = (Path(__file__).resolve().parents[3] / "pyproject.toml").read_text()
    group = toml.split('[project.entry-points."btmission.providers"]')[1].split("\n[")[0]
    assert 'fake = "btmission.backends.fake:fake_provider"' in group
    assert installed_providers()["fake"].value == "btmission.backends.fake:fake_provider"


def test_sim_is_found_by_an_install_without_the_entry_point(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr(metadata, "entry_points", lambda group: [])
    assert list(installed_providers()) == ["sim", "fake", "mavlink"]
    assert provider_factory("sim") is sim_provider
    assert provider_factory("fake") is fake_provider


def test_a_scheme_installed_twice_counts_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """The worktree and the main checkout can both expose the same dist-info."""
    ep = metadata.EntryPoint(
        "sim", "btmission.backends.sim_provider:sim_provider", ENTRY_POINT_GROUP
    )

    def twice(group: str) -> Sequence[metadata.EntryPoint]:
        return [ep, ep] if group == ENTRY_POINT_GROUP else []

    monkeypatch.setattr(metadata, "entry_points", twice)
    assert list(installed_providers()) == ["sim", "fake", "mavlink"]


def test_an_unknown_scheme_has_no_factory() -> None:
    with pytest.raises(ProviderError, match=r"no vehicle provider for scheme 'gazebo'.*'sim'"):
        provider_factory("gazebo")


@pytest.mark.parametrize(
    ("url", "scheme"),
    [
        ("sim", "sim"),
        ("mavlink+udp://127.0.0.1:14540", "mavlink"),
        ("mavlink+serial:///dev/ttyACM0", "mavlink"),
        ("gz://world/x", "gz"),
    ],
)
def test_the_scheme_is_the_part_before_the_address(url: str, scheme: str) -> None:
    ref = VehicleRef.parse(url)
    assert ref.scheme == scheme and ref.url == str(ref) == url and ref.well_formed


def test_a_reference_keeps_transport_and_address_for_its_provider() -> None:
    ref = VehicleRef.parse("mavlink+udp://127.0.0.1:14540?sysid=2")
    assert (ref.scheme, ref.transport, ref.address) == ("mavlink", "udp", "127.0.0.1:14540?sysid=2")
    assert VehicleRef.parse("sim") == SIM and SIM.address == "" and SIM.transport == ""
    odd = VehicleRef.parse("mavlink:udp:127.0.0.1:14540")  # pymavlink's form: the provider explains
    assert odd.scheme == "mavlink" and not odd.well_formed
    for bad in ("Gazebo sim", "", "9lives", "sim two"):
        with pytest.raises(ValueError, match="expected 'sim' or a vehicle provider's URL"):
            VehicleRef.parse(bad)


# ------------------------------------------------------------------------------ validate
def test_validate_refuses_an_unknown_scheme_at_its_line(tmp_path: Path) -> None:
    path = write(tmp_path, "sim", "'gz://127.0.0.1:11345'")
    code, out = validate(path)
    assert code == 2
    assert (
        f"{path}:7:58: agents[1].backend: backend 'gz://127.0.0.1:11345': no vehicle provider "
        "for scheme 'gz' is installed; installed: 'sim', 'fake', 'mavlink' (entry-point group 'btmission.providers')"
    ) in out


def test_validate_accepts_mavlink_vehicles(tmp_path: Path) -> None:
    path = write(tmp_path, "'mavlink+udp://127.0.0.1:14540'", "'mavlink+udp://127.0.0.1:14541'")
    code, out = validate(path)
    assert code == 0, out


def test_validate_refuses_mixing_mavlink_and_sim(tmp_path: Path) -> None:
    path = write(tmp_path, "sim", "'mavlink+udp://127.0.0.1:14541'")
    code, out = validate(path)
    assert code == 2
    assert f"{path}:7:58: agents[1].backend: backend 'mavlink+udp://127.0.0.1:14541'" in out
    assert "uses 'sim'" in out


def test_validate_accepts_an_installed_plugin_scheme(
    tmp_path: Path, replay_installed: None
) -> None:
    code, out = validate(write(tmp_path, "'replay://log-1'", "'replay://log-2'"))
    assert code == 0, out
    assert Recording.made == []  # validate looks entry points up, never loads or builds them


def test_validate_refuses_a_mixed_fleet(tmp_path: Path, replay_installed: None) -> None:
    path = write(tmp_path, "sim", "'replay://log-1'")
    code, out = validate(path)
    assert code == 2
    assert (
        f"{path}:7:58: agents[1].backend: backend 'replay://log-1': agent 'G1' uses 'sim'; every "
        "agent of a mission must use the same vehicle provider (a run steps one provider, on one "
        "clock: simulated time, or the wall clock for real vehicles)"
    ) in out


def test_run_refuses_what_validate_refuses(tmp_path: Path) -> None:
    path = write(tmp_path, "sim", "'gz://x'")
    result = CliRunner().invoke(
        cli, ["run", str(path), "--log", str(tmp_path), "--until", "1", "--no-png", "--quiet"]
    )
    assert result.exit_code == 2, result.output
    assert f"{path}:7:58: agents[1].backend: backend 'gz://x': no vehicle provider" in result.output
    assert not list(tmp_path.glob("*.jsonl"))


# ------------------------------------------------------------------------------ a run
def test_a_run_gets_its_vehicles_from_the_agents_provider(
    tmp_path: Path, replay_installed: None
) -> None:
    text = MISSION.format(first="'replay://a'", second="'replay://b'")
    run = MissionRun(load_mission_text(text, str(tmp_path / "m.yaml")))
    [made] = Recording.made
    assert run.provider is made and run.clock is made.clock and not run.realtime
    assert [(a, k, u) for a, k, _, u, _ in made.attached] == [
        ("G1", VehicleKind.GROUND, "replay://a"),
        ("G2", VehicleKind.GROUND, "replay://b"),
    ]
    # the navigator's speed; nothing of MAVLink's frames (the MAVLink provider reads them)
    assert made.attached[0][4] == AttachOptions(v_max=run.nav_config.speed_m_s)
    # the kernels loaded while the run is built, before any link opens or vehicle comes
    assert made.phases == ["warm_up", "prepare", "attach", "attach", "start"]
    result = run.run()
    assert result.reason == "completed" and result.steps == len(made.steps) > 0
    assert set(made.steps) == {run.dt}
    run.close()
    assert made.closed


def test_the_sim_provider_steps_whole_simulator_steps(tmp_path: Path) -> None:
    text = MISSION.format(first="sim", second="sim")
    mission = load_mission_text(text, str(tmp_path / "m.yaml"))
    made = sim_provider(mission, VoxelMap.empty((10, 10, 4), 0.5), 0)
    assert made.step(0.25) == [] and made.clock.now() == pytest.approx(0.25)
    with pytest.raises(ValueError, match=r"multiple of the simulator's step 0\.05 s"):
        made.step(0.07)


# ------------------------------------------------------------------------------ layering
def test_the_backend_interface_imports_no_algorithm() -> None:
    code = textwrap.dedent(
        """
        import sys
        import btmission.vehicles.base, btmission.vehicles.provider
        print(" ".join(sorted(m for m in sys.modules if m.startswith("btmission"))))
        """
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60
    ).stdout.split()
    assert "btmission.vehicles.base" in out and "btmission.types" in out
    algorithms = ("control", "planning", "localization", "allocation", "synthesis", "runtime")
    leaked = [m for m in out if m.split(".")[1:2] and m.split(".")[1] in algorithms]
    assert leaked == [], leaked


# ------------------------------------------------------------------------------ plugins and phases
def _replay_address(ref: VehicleRef) -> str | None:
    return None if ref.address.startswith("ok") else f"replay wants ok..., got '{ref.address}'"


CHECKED = ProviderPlugin(recording_provider, check_address=_replay_address)


class NoStart(SimProvider):
    """A provider written for an older btmission: no start phase."""

    start = None  # type: ignore[assignment]


def no_start_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> NoStart:
    return NoStart(sim_provider(mission, voxel_map, seed).sim)


def _install(monkeypatch: pytest.MonkeyPatch, scheme: str, value: str) -> None:
    real = registry.installed_providers

    def installed() -> dict[str, metadata.EntryPoint]:
        return {**real(), scheme: metadata.EntryPoint(scheme, value, ENTRY_POINT_GROUP)}

    monkeypatch.setattr(registry, "installed_providers", installed)


def test_only_the_provider_reads_an_address_and_validate_asks_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _install(monkeypatch, "replay", f"{__name__}:CHECKED")
    path = tmp_path / "m.yaml"
    path.write_text(MISSION.format(first="'replay://ok-1'", second="'replay://bad'"))
    code, out = validate(path)
    assert code == 2
    assert f"{path}:7:58: agents[1].backend: replay wants ok..., got 'bad'" in out
    assert "agents[0]" not in out  # the first one's address is fine by its provider
    path.write_text(MISSION.format(first="'replay://ok-1'", second="'replay://ok-2'"))
    assert validate(path)[0] == 0


def test_a_provider_without_a_check_takes_scheme_colon_slash_slash_only(
    tmp_path: Path, replay_installed: None
) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(MISSION.format(first="'replay:a'", second="'replay://b'"))
    code, out = validate(path)
    assert code == 2 and f"{path}:6:58: agents[0].backend: expected 'sim' or a vehicle" in out


def test_a_provider_lacking_a_phase_is_refused_by_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _install(monkeypatch, "nostart", f"{__name__}:no_start_provider")
    text = MISSION.format(first="'nostart://a'", second="'nostart://b'")
    with pytest.raises(
        ProviderError, match=r"'nostart' vehicle provider \(NoStart\) has no start\(\)"
    ):
        MissionRun(load_mission_text(text, str(tmp_path / "m.yaml")))


# ------------------------------------------------------------------------------ attaching the fleet
class Refusing(SimProvider):
    """A provider whose vehicles at ``refusing://gone...`` are not there (from ``attach``)."""

    def attach(
        self,
        agent_id: str,
        kind: VehicleKind,
        start: Vec3,
        ref: VehicleRef = SIM,
        options: AttachOptions = AttachOptions(),
    ) -> Vehicle:
        if ref.address.startswith("gone"):
            raise VehicleUnavailable(f"{agent_id}: nothing answers at {ref.url}")
        return super().attach(agent_id, kind, start, ref, options)


def refusing_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> Refusing:
    return Refusing(sim_provider(mission, voxel_map, seed).sim)


class Unnamed(Refusing):
    """A provider whose whole fleet fails at once, naming no agent."""

    def attach_all(self, requests: Sequence[AttachRequest]) -> list[Vehicle]:
        raise VehicleUnavailable("the fleet's radio is off")


def unnamed_provider(mission: Mission, voxel_map: VoxelMap, seed: int) -> Unnamed:
    return Unnamed(sim_provider(mission, voxel_map, seed).sim)


def test_the_base_attaches_the_fleet_in_order_naming_the_vehicle_that_failed(
    tmp_path: Path,
) -> None:
    provider = refusing_provider(
        load_mission_text(MISSION.format(first="sim", second="sim"), str(tmp_path / "m.yaml")),
        VoxelMap.empty((20, 20, 4), 0.5),
        0,
    )
    fine = [
        AttachRequest("G1", VehicleKind.GROUND, (2.0, 2.0, 0.0)),
        AttachRequest("D1", VehicleKind.MULTIROTOR, (4.0, 2.0, 0.0)),
    ]
    assert [v.id for v in provider.attach_all(fine)] == ["G1", "D1"]
    gone = VehicleRef.parse("refusing://gone-1")
    with pytest.raises(VehicleUnavailable) as info:
        provider.attach_all([AttachRequest("G3", VehicleKind.GROUND, (6.0, 2.0, 0.0), gone)])
    assert info.value.failures == {"G3": "G3: nothing answers at refusing://gone-1"}


def test_a_run_names_each_vehicle_that_could_not_be_had_at_its_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _install(monkeypatch, "refusing", f"{__name__}:refusing_provider")
    path = write(tmp_path, "'refusing://here'", "'refusing://gone-2'")
    with pytest.raises(VehicleUnavailable) as info:
        MissionRun(load_mission_text(path.read_text(), str(path)))
    assert str(info.value) == (
        f"{path}:7:58: agents[1].backend: G2: nothing answers at refusing://gone-2"
    )
    assert info.value.failures == {"G2": "G2: nothing answers at refusing://gone-2"}
    _install(monkeypatch, "refusing", f"{__name__}:unnamed_provider")
    with pytest.raises(VehicleUnavailable) as info:
        MissionRun(load_mission_text(path.read_text(), str(path)))
    assert str(info.value) == f"{path}:6:3: agents: the fleet's radio is off"
