"""The sections of a mission file that describe where it runs, not what it does: the world
(``world:`` — a generated or a file map, its geodetic origin, its topological map) and the
runtime (``runtime:`` — the controller, the embedded simulator, the MAVLink provider, the
libraries' settings). :mod:`btmission.spec.mission` builds the whole file's model from them.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Discriminator,
    Field,
    Tag,
    ValidationInfo,
    field_validator,
)

from btmission.limits import grid_shape
from btmission.spec.common import (
    FiniteFloat,
    Identifier,
    Int,
    number_problem,
    shown,
)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Vec3 = Annotated[
    tuple[FiniteFloat, FiniteFloat, FiniteFloat], Field(description="[x, y, z] in metres")
]


class GeneratedMap(_Strict):
    """A procedurally generated map (the world-map component provides the generators)."""

    generate: Literal["mine", "empty", "warehouse"] = Field(
        description="Generator: an underground mine, free space, or a warehouse floor with "
        "rows of shelves."
    )
    seed: Int = Field(0, ge=0, description="Random seed; the same seed gives the same map.")
    size: tuple[FiniteFloat, FiniteFloat, FiniteFloat] = Field(
        description="Extent [x, y, z] in metres."
    )

    @field_validator("size")
    @classmethod
    def _positive(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if min(v) <= 0:
            raise ValueError("every size component must be > 0")
        return v


class FileMap(_Strict):
    """A map read from a file (.npz voxel map, .ply or .pcd point cloud), relative to the mission."""

    file: str = Field(description="Path to the map, relative to the mission file.")


def _map_kind(v: Any) -> str:
    """The tag of a ``map``: a mapping while validating, a model while serialising."""
    return (
        "File" if isinstance(v, FileMap) or (isinstance(v, dict) and "file" in v) else "Generated"
    )


class GeodeticSpec(_Strict):
    """Where the world's (0, 0, 0) is on the globe (world +y is true north)."""

    lat: FiniteFloat = Field(
        description="Latitude of the world origin, degrees north, -90 < lat < 90."
    )
    lon: FiniteFloat = Field(
        description="Longitude of the world origin, degrees east, -180 <= lon <= 180."
    )
    alt: FiniteFloat = Field(0.0, description="Altitude of world z = 0 (m).")

    @field_validator("lat", mode="before")
    @classmethod
    def _lat(cls, v: Any) -> Any:
        if number_problem(v) is None and not -90.0 < v < 90.0:
            raise ValueError(f"expected a latitude in degrees, -90 < lat < 90 (got {shown(v)})")
        return v

    @field_validator("lon", mode="before")
    @classmethod
    def _lon(cls, v: Any) -> Any:
        if number_problem(v) is None and not -180.0 <= v <= 180.0:
            raise ValueError(
                f"expected a longitude in degrees, -180 <= lon <= 180 (got {shown(v)})"
            )
        return v


class WorldSpec(_Strict):
    map: Annotated[
        Annotated[GeneratedMap, Tag("Generated")] | Annotated[FileMap, Tag("File")],
        Discriminator(_map_kind),
    ] = Field(description="{generate: mine, seed: 7, size: [x, y, z]} or {file: path}")
    resolution: FiniteFloat = Field(0.5, gt=0, description="Voxel size in metres.")
    topomap: str | None = Field(
        None,
        description="Topological map for GA fleet dispatch (seed 004): a built-in map (mine, "
        "static_npr, static_spr) or a map YAML file relative to the mission. Default: none.",
    )
    origin: GeodeticSpec | None = Field(
        None,
        description="Where world (0, 0, 0) is on the globe, {lat, lon, alt}, for MAVLink "
        "vehicles with GPS (or given a GPS origin); world +y is north. Ignored by sim.",
    )

    @field_validator("resolution")
    @classmethod
    def _voxel_budget(cls, v: float, info: ValidationInfo) -> float:
        """A finite resolution, and a generated map within the voxel budget (before building)."""
        m = info.data.get("map")
        grid_shape(m.size if isinstance(m, GeneratedMap) else (1.0, 1.0, 1.0), v)
        return v


def _setting_value(v: Any) -> Any:
    """A ``runtime.settings`` value: a finite number, a string or true/false."""
    if isinstance(v, (bool, str)):
        return v
    if isinstance(v, (int, float)):
        problem = number_problem(v)
        if problem:
            raise ValueError(problem)
        return v
    raise ValueError(f"expected a number, a string or true/false (got {v!r})")


SettingValue = Annotated[int | float | str | bool, BeforeValidator(_setting_value)]


class ArtifactSpec(_Strict):
    """An object of interest the simulator places in the world (seed 002 §3.3.1)."""

    label: Identifier = Field(description="Class of the object, e.g. survivor, backpack.")
    position: Vec3
    size_m: FiniteFloat = Field(0.5, gt=0, description="Width of the object in metres.")


class SimSpec(_Strict):
    """Settings of the embedded simulator (``btmission run``; ignored by other backends)."""

    step_s: FiniteFloat = Field(0.05, gt=0, le=0.2, description="Fixed simulation time step (s).")
    lidar_range_m: FiniteFloat = Field(
        2.0,
        gt=0,
        description="Range of the simulated LiDAR (m); the APF only uses points within 1.6 m.",
    )
    dust_points: Int = Field(
        0, ge=0, description="Dust outliers added to each LiDAR scan near the vehicle."
    )
    detection_noise_px: FiniteFloat = Field(
        2.0, ge=0, description="Standard deviation of artifact detection boxes (pixels)."
    )
    max_speed_m_s: FiniteFloat = Field(
        3.0,
        gt=0,
        description="Horizontal speed limit of the simulated autopilot's position and velocity"
        " loops (m/s, PX4 MPC_XY_VEL_MAX); the NMPC's attitude setpoints are not limited.",
    )
    velocity_noise: FiniteFloat = Field(
        0.0,
        ge=0,
        le=0.5,
        description="Ground robots drive (1 + e) times their commanded speed and turn rate, e a "
        "seeded random error with this standard deviation (0.05: 5 %), correlated over "
        "velocity_noise_tau_s (wheel slip, motor speed loops); 0: exactly the command.",
    )
    velocity_noise_tau_s: FiniteFloat = Field(
        1.0, gt=0, le=60, description="Correlation time of velocity_noise's error (s)."
    )
    pose_noise_m: FiniteFloat = Field(
        0.0,
        ge=0,
        le=0.5,
        description="Standard deviation of the x and y the vehicles report about their true "
        "position (m; the localisation's error, drawn every step, seeded).",
    )
    heading_noise_rad: FiniteFloat = Field(
        0.0,
        ge=0,
        le=0.5,
        description="Standard deviation of the heading the vehicles report about their true "
        "heading (rad; drawn every step, seeded).",
    )
    artifacts: list[ArtifactSpec] = Field(
        default_factory=list, description="Objects the simulated camera can detect (COMPRA)."
    )


class MavlinkSpec(_Strict):
    """How the ``mavlink`` provider talks to the agents' autopilots (docs/mavlink.md; ignored
    by other providers). The signing key never goes here: ``run --mavlink-key-file`` or the
    environment (``BTMISSION_MAVLINK_KEY_FILE``, ``BTMISSION_MAVLINK_KEY``)."""

    connect_timeout_s: FiniteFloat = Field(
        120.0,
        gt=0,
        le=600,
        description="Wall time to wait for the vehicles, all connected at once: each one's "
        "heartbeat, answers and position estimate (ArduPilot SITL's EKF takes about 40 s with "
        "simulated GPS).",
    )
    setpoint_hz: FiniteFloat = Field(
        20.0,
        gt=2,
        le=200,
        description="Setpoints streamed per second to each vehicle (PX4 needs > 2 Hz).",
    )
    telemetry_hz: FiniteFloat = Field(
        50.0,
        gt=0,
        le=200,
        description="Position and attitude messages asked of each vehicle per second.",
    )
    heartbeat_timeout_s: FiniteFloat = Field(
        3.0,
        gt=0,
        le=60,
        description="Wall time without a heartbeat after which a vehicle's link is lost "
        "(whatever time_scale).",
    )
    ack_timeout_s: FiniteFloat = Field(
        1.0, gt=0, le=30, description="Wall time to wait for a COMMAND_ACK before sending again."
    )
    hover_thrust: FiniteFloat = Field(
        0.5,
        gt=0,
        le=1,
        description="Normalised hover throttle of attitude setpoints (PX4 MPC_THR_HOVER, "
        "ArduPilot MOT_THST_HOVER).",
    )
    time_scale: FiniteFloat = Field(
        1.0,
        gt=0,
        le=50,
        description="How much faster than real time the vehicles run (mavsim --speed, ArduPilot "
        "SITL --speedup, PX4_SIM_SPEED_FACTOR); 1 for real vehicles.",
    )
    on_stop: Literal["land", "hold"] = Field(
        "land",
        description="What a flying vehicle is told when the run stops (the mission ends, a time "
        "limit, Ctrl-C or SIGTERM): hold where it is, then land (land), or only hold (hold).",
    )
    map_sensors: bool = Field(
        False,
        description="Give agents simulated sensors by ray-casting the mission map at the pose "
        "each vehicle reports (for SITL and tests; real sensors come from drivers).",
    )


class RuntimeSpec(_Strict):
    """How ``btmission run`` executes the mission (all optional)."""

    tick_hz: FiniteFloat = Field(10.0, gt=0, le=100, description="Behaviour-tree ticks per second.")
    controller: Literal["nmpc", "track"] = Field(
        "nmpc",
        description="Path following: nmpc (seed 002/003 NMPC with APF) or track (lightweight "
        "tracking controller, for large fleets).",
    )
    max_duration_s: FiniteFloat = Field(
        3600.0, gt=0, description="The run stops at this mission time if it has not ended."
    )
    status_hz: FiniteFloat = Field(
        2.0, gt=0, le=50, description="Agent status and pose events per second in the log."
    )
    risk_radius_m: FiniteFloat = Field(1.5, ge=0, description="D*+ risk radius r (eq. 3).")
    unknown_cost: FiniteFloat = Field(10.0, ge=0, description="D*+ unknown-voxel cost c_u (eq. 4).")
    path_fields_mb: int = Field(
        1024,
        ge=16,
        le=1_048_576,
        description="Memory for the bidders' D*+ cost-to-goal fields (MB; one field per task "
        "goal, 4 bytes a voxel): a mission whose goals need more searches evicted ones again.",
    )
    settings: dict[Identifier, SettingValue] = Field(
        default_factory=dict,
        description="Settings of the libraries' implementations, e.g. {speed_m_s: 1.5}.",
    )
    sim: SimSpec = SimSpec()
    mavlink: MavlinkSpec = MavlinkSpec()
