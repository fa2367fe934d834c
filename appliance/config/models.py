"""The vehicle profile: one validated model of everything the daemon needs to know.

Every quantity carries its unit in its name (``wheelbase_m``, ``max_steer_rate_deg_per_s``)
so a TOML file reads unambiguously on the vehicle, where a wrong unit is a crash rather
than a bug report. Bounds are physical plausibility limits, not tuning advice: they catch
typos (a wheelbase of 350 instead of 3.5) before the vehicle moves. Models forbid unknown
fields, because a misspelled key silently falling back to a default is exactly the kind
of mistake that must not reach a nine-ton vehicle.
"""

from __future__ import annotations

import ipaddress
import math
from datetime import UTC, datetime
from enum import StrEnum
from typing import Annotated, Literal, Self

from pydantic import AwareDatetime, BaseModel, ConfigDict, Field, field_validator, model_validator

from appliance.config.forklift_models import Forks, PalletGuidanceSettings, TabletPageSettings
from appliance.config.palm_tree_models import PalmTreeDriveSettings, palm_tree_drive_problems
from appliance.config.pedal_models import PedalSweepSettings, SimPedals, sweep_limit_problems
from appliance.config.tuning_models import LookaheadTuningSettings
from drivers.actuators.steering_model import ServoParams
from drivers.gnss.client import BAUDRATES_BPS as GNSS_BAUDRATES_BPS
from drivers.pc104.endpoint import SLCAN_BITRATES_BPS, CanInterface
from drivers.ptylink import SIM_PORT_PREFIX


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, validate_default=True)


Port = Annotated[int, Field(ge=1, le=65535)]


class VehicleKind(StrEnum):
    """Steering layouts the guidance layer knows how to track."""

    FLATBED = "flatbed"  # multi-wheel transporter: straight, crab, rear steer, turn-around
    FOUR_WHEEL_COUNTER_STEER = "four_wheel_counter_steer"  # proportional 4WS (Husky)
    FRONT_STEER = "front_steer"  # a single steered front axle
    # Kinouchi et al.'s automated guided forklift: the rear axle steers, forks ahead.
    FORKLIFT = "forklift"


class SensorMount(_Model):
    """Pose of a sensor in the vehicle frame.

    x forward, y left, z up; the origin is the vehicle's geometric centre (midway between
    the steered axles), the reference Qian et al. convert every pose to and the point the
    kinematics of the simulated vehicle integrate.
    """

    x_m: float = Field(0.0, ge=-30.0, le=30.0)
    y_m: float = Field(0.0, ge=-10.0, le=10.0)
    z_m: float = Field(0.5, ge=-2.0, le=10.0)
    yaw_deg: float = Field(0.0, ge=-180.0, le=180.0)


class Geometry(_Model):
    """Chassis geometry used by kinematics, pure pursuit and the simulated vehicle."""

    wheelbase_m: float = Field(3.5, gt=0.5, le=30.0)
    track_width_m: float = Field(2.2, gt=0.5, le=6.0)
    length_m: float = Field(5.5, gt=0.5, le=40.0)
    width_m: float = Field(2.5, gt=0.5, le=6.0)
    # Rear-to-front steer ratio of proportional counter-steer (Stanley et al., eq. 1):
    # phi_r = -k * phi_f. 0 means front steer only.
    counter_steer_ratio_k: float = Field(1.0, ge=0.0, le=1.5)
    # Pure pursuit tracks a point ahead of the vehicle centre (Stanley et al., Fig. 8).
    anchor_point_forward_m: float = Field(1.5, ge=0.0, le=20.0)
    # Sideslip gain G_ss = 1 / (1 + (v / V_char)^2) (Stanley et al.).
    characteristic_speed_mps: float = Field(12.0, gt=0.5, le=60.0)
    scanner_left_mount: SensorMount = SensorMount(x_m=2.6, y_m=1.1, yaw_deg=45.0)
    scanner_right_mount: SensorMount = SensorMount(x_m=2.6, y_m=-1.1, yaw_deg=-45.0)


class Limits(_Model):
    """Actuation limits the safety layer enforces whatever the autopilot asks."""

    max_steer_angle_deg: float = Field(30.0, gt=0.0, le=60.0)
    max_steer_rate_deg_per_s: float = Field(20.0, gt=0.0, le=180.0)
    max_speed_mps: float = Field(4.5, gt=0.0, le=20.0)
    max_engage_speed_mps: float = Field(4.5, gt=0.0, le=20.0)
    throttle_min_pct: float = Field(0.0, ge=0.0, le=100.0)
    throttle_max_pct: float = Field(40.0, gt=0.0, le=100.0)
    max_throttle_rate_pct_per_s: float = Field(50.0, gt=0.0, le=1000.0)
    brake_min_pct: float = Field(0.0, ge=0.0, le=100.0)
    brake_max_pct: float = Field(100.0, gt=0.0, le=100.0)

    @model_validator(mode="after")
    def _ranges_are_ordered(self) -> Self:
        if self.throttle_min_pct >= self.throttle_max_pct:
            raise ValueError(
                "throttle_min_pct must be below throttle_max_pct "
                f"(got {self.throttle_min_pct} >= {self.throttle_max_pct})"
            )
        if self.brake_min_pct >= self.brake_max_pct:
            raise ValueError(
                "brake_min_pct must be below brake_max_pct "
                f"(got {self.brake_min_pct} >= {self.brake_max_pct})"
            )
        if self.max_engage_speed_mps > self.max_speed_mps:
            raise ValueError(
                "max_engage_speed_mps must not exceed max_speed_mps "
                f"(got {self.max_engage_speed_mps} > {self.max_speed_mps})"
            )
        return self


class ColaDialect(StrEnum):
    """The SOPAS encoding the scanner is set to (SOPAS ET, or `sWN EIHstCola`).

    CoLa-B is binary with a checksum: about a third of CoLa-A's bytes and of its decode
    time, and a corrupted telegram is detected rather than misread.
    """

    COLA_A = "cola-a"
    COLA_B = "cola-b"


class Lms111Endpoint(_Model):
    """One SICK LMS111 on Ethernet."""

    host: str = Field("127.0.0.1", min_length=1)
    port: Port = 2111
    cola_dialect: ColaDialect = ColaDialect.COLA_A
    scan_frequency_hz: Annotated[int, Field(ge=25, le=50)] = 50
    angular_resolution_deg: float = Field(0.5, ge=0.25, le=0.5)

    @model_validator(mode="after")
    def _supported_modes(self) -> Self:
        # The LMS111 runs 25 Hz at 0.25 deg or 50 Hz at 0.5 deg (25 Hz at 0.5 deg too);
        # it refuses 50 Hz at 0.25 deg at start-up, so refuse it here, before the vehicle.
        if self.scan_frequency_hz not in (25, 50):
            raise ValueError(f"scan_frequency_hz must be 25 or 50 (got {self.scan_frequency_hz})")
        if self.angular_resolution_deg not in (0.25, 0.5):
            raise ValueError(
                f"angular_resolution_deg must be 0.25 or 0.5 (got {self.angular_resolution_deg})"
            )
        if self.scan_frequency_hz == 50 and self.angular_resolution_deg == 0.25:
            raise ValueError(
                "the LMS111 cannot scan at 50 Hz with 0.25 deg resolution: "
                "use 25 Hz with 0.25 deg or 50 Hz with 0.5 deg"
            )
        return self


class CanEndpoint(_Model):
    """The link to the vehicle's PC104 lower-level controller."""

    interface: CanInterface = CanInterface.VIRTUAL
    channel: str = Field("dbw-sim", min_length=1)
    bitrate_bps: Annotated[int, Field(ge=10_000, le=1_000_000)] = 500_000

    @model_validator(mode="after")
    def _slcan_bitrate(self) -> Self:
        if self.interface is CanInterface.SLCAN and self.bitrate_bps not in SLCAN_BITRATES_BPS:
            raise ValueError(
                f"an SLCAN adapter cannot run at {self.bitrate_bps} bit/s; choose one of "
                + ", ".join(str(b) for b in SLCAN_BITRATES_BPS)
            )
        return self


class SerialEndpoint(_Model):
    """One actuator board. ``sim://NAME`` selects the in-process twin on a pseudo-terminal."""

    port: str = Field(min_length=1)
    baudrate_bps: Annotated[int, Field(ge=1200, le=4_000_000)] = 115_200


class GnssEndpoint(_Model):
    """A GNSS/INS receiver speaking NMEA 0183 on a serial port (``sim://gnss``: the twin).

    ``receiver_latency_s`` is the time from the position's measurement to its last
    sentence arriving (the receiver's manual, or a measurement): each fix is stamped
    that much before it was received, and the vehicle has moved speed x latency since."""

    port: str = Field(min_length=1)
    baudrate_bps: int = 115_200
    receiver_latency_s: float = Field(ge=0.0, le=1.0)

    @model_validator(mode="after")
    def _standard_baud(self) -> Self:
        # Receivers offer the standard rates only; a typo here would open the port at a
        # rate nothing speaks and show up later as "no sentences", far from its cause.
        if self.baudrate_bps not in GNSS_BAUDRATES_BPS:
            raise ValueError(
                f"baudrate_bps {self.baudrate_bps} is not a standard NMEA rate: "
                f"one of {', '.join(str(b) for b in GNSS_BAUDRATES_BPS)}"
            )
        return self


class Devices(_Model):
    lms111_left: Lms111Endpoint = Lms111Endpoint(port=2111)
    lms111_right: Lms111Endpoint = Lms111Endpoint(port=2112)
    can: CanEndpoint = CanEndpoint()
    steering_serial: SerialEndpoint = SerialEndpoint(port="sim://steering")
    throttle_serial: SerialEndpoint = SerialEndpoint(port="sim://throttle")
    brake_serial: SerialEndpoint = SerialEndpoint(port="sim://brake")
    panel_serial: SerialEndpoint = SerialEndpoint(port="sim://panel")
    gnss: GnssEndpoint | None = None  # a vehicle that follows routes has one

    @model_validator(mode="after")
    def _scanners_apart(self) -> Self:
        # Each real LMS111 listens on 2111 at its own address; two at one address and port
        # would be one scanner read twice (and two simulated ones cannot both listen there).
        left, right = self.lms111_left, self.lms111_right
        if (left.host, left.port) == (right.host, right.port):
            raise ValueError(
                f"lms111_left and lms111_right are both at {left.host}:{left.port}: "
                "give each scanner its own host or port"
            )
        return self


class Rates(_Model):
    control_hz: float = Field(50.0, ge=10.0, le=200.0)
    pc104_command_hz: float = Field(50.0, ge=10.0, le=200.0)
    status_report_hz: float = Field(1.0, gt=0.0, le=10.0)


class Staleness(_Model):
    """Age limits per input: a critical input older than this is a fault within one cycle."""

    scan_max_age_s: float = Field(0.1, gt=0.0, le=2.0)
    pose_max_age_s: float = Field(0.1, gt=0.0, le=2.0)
    pc104_status_max_age_s: float = Field(0.1, gt=0.0, le=2.0)
    steering_pot_max_age_s: float = Field(0.05, gt=0.0, le=2.0)
    actuator_board_max_age_s: float = Field(0.1, gt=0.0, le=2.0)
    panel_max_age_s: float = Field(0.2, gt=0.0, le=2.0)


class SafetyTimeouts(_Model):
    """How the vehicle is brought to rest, how long each step may take, and the thresholds
    of the safety rules (override detection, steering consistency, link error budget)."""

    safe_stop_decel_mps2: float = Field(1.5, gt=0.0, le=8.0)
    estop_decel_mps2: float = Field(4.0, gt=0.0, le=10.0)
    # Deceleration the vehicle reaches at 100 % brake: maps a deceleration to a brake level.
    full_brake_decel_mps2: float = Field(5.0, gt=0.0, le=12.0)
    # How fast the safe-stop brake is applied (0 -> target), so a fault at speed does not
    # lock the wheels of a loaded vehicle; the e-stop applies full brake at once.
    safe_stop_brake_ramp_pct_per_s: float = Field(200.0, gt=0.0, le=10_000.0)
    # Steering override: |measured - commanded| tyre angle above the threshold for the
    # dwell time while the servo pushes at least min torque means hands on the wheel;
    # it ends below the release threshold (hysteresis).
    steer_override_threshold_deg: float = Field(4.0, gt=0.0, le=30.0)
    steer_override_release_deg: float = Field(2.0, gt=0.0, le=30.0)
    steer_override_dwell_s: float = Field(0.1, ge=0.0, le=2.0)
    steer_override_min_torque_nm: float = Field(8.0, ge=0.0, le=30.0)
    # Near the steering stops a deviation towards the stop is the stop, not the operator.
    steer_stop_margin_deg: float = Field(1.5, ge=0.0, le=10.0)
    # Steering consistency: beyond the tolerance for this long without an override means
    # the servo is not steering (torque loss, slip): a steering fault.
    steer_tracking_tolerance_deg: float = Field(3.0, gt=0.0, le=30.0)
    steer_tracking_fault_after_s: float = Field(0.5, gt=0.0, le=5.0)
    # A pedal more than this above what our actuator pulls is the operator's foot.
    pedal_override_margin_pct: float = Field(8.0, gt=0.0, le=50.0)
    # PC104 link: every CRC/counter/length error adds one, every good status frame takes
    # one away (panda); at the limit the link is a fault.
    pc104_error_budget_limit: Annotated[int, Field(ge=1, le=1000)] = 10
    # The PC104 and the boards stop on their own when commands stop for this long.
    lower_layer_command_timeout_s: float = Field(0.1, gt=0.0, le=1.0)
    # Shutdown must finish within 1 s in total; this is the budget for services to unwind.
    shutdown_grace_s: float = Field(0.6, gt=0.0, le=0.9)

    @model_validator(mode="after")
    def _thresholds_are_ordered(self) -> Self:
        if self.steer_override_release_deg >= self.steer_override_threshold_deg:
            raise ValueError(
                "steer_override_release_deg must be below steer_override_threshold_deg "
                f"(got {self.steer_override_release_deg} >= {self.steer_override_threshold_deg})"
            )
        if self.safe_stop_decel_mps2 > self.full_brake_decel_mps2:
            raise ValueError(
                "safe_stop_decel_mps2 must not exceed full_brake_decel_mps2 "
                f"(got {self.safe_stop_decel_mps2} > {self.full_brake_decel_mps2})"
            )
        return self


class Engagement(_Model):
    """How the operator engages automatic control (Stanley et al., Fig. 4)."""

    # Each + or - press while speed hold is on changes the set speed by this much.
    speed_step_mps: float = Field(0.25, gt=0.0, le=2.0)
    # The set speed never exceeds this (and never limits.max_speed_mps).
    max_set_speed_mps: float = Field(3.0, gt=0.0, le=20.0)
    # How fast the speed set-point sent to the PC104 may rise (falling is not limited).
    max_accel_mps2: float = Field(0.5, gt=0.0, le=5.0)
    # Kinouchi et al.'s guidance mode: the vehicle moves only while the operator holds
    # the engage button; on release it stops within hold_to_move_stop_distance_m.
    hold_to_move: bool = False
    hold_to_move_stop_distance_m: float = Field(1.0, gt=0.0, le=20.0)
    # SELF_CHECK waits this long for every critical input before it fails.
    self_check_timeout_s: float = Field(10.0, gt=0.0, le=120.0)
    # The autopilot's steering/speed source until guidance provides one: by name.
    autopilot_source: str = Field("hold_straight", min_length=1)


class Docking(_Model):
    """The flat-bed's docking to its launcher (Qian et al. 4.1-4.2): the teeth on the
    vehicle's front end, the launcher's landmarks, and where docking may be engaged.

    The launcher frame: origin at the centre of the front board's face, +x into the
    launcher, +y to the left of a vehicle facing it. Defaults are the built-in site's.
    """

    # The front end's centre ahead of the vehicle's geometric centre; None: half the length.
    front_end_forward_m: float | None = Field(None, gt=0.0, le=30.0)
    teeth_lateral_m: float = Field(1.0, ge=0.0, le=5.0)  # the two teeth at ±this
    tooth_insertion_m: float = Field(0.15, gt=0.0, le=2.0)  # how far a tooth sticks out
    trough_clearance_m: float = Field(0.01, gt=0.0, le=0.2)  # a trough is 2x this wider
    standoff_m: float = Field(0.0, ge=0.0, le=20.0)  # gap 0: the front end this far out
    max_speed_mps: float = Field(0.3, gt=0.0, le=2.0)
    # Who turns the pose error into wheel angles: "hl" sends the angles in HL_MotionCommand
    # (any PC104 follows them); "pc104" also sends HL_Pose and HL_ExpectedPose and lets a
    # PC104 that runs its own PID per pattern (Qian et al.'s) steer on them.
    pose_loop: Literal["hl", "pc104"] = "hl"
    # The automatic navigation zone: docking is engaged only inside it.
    zone_max_gap_m: float = Field(12.0, gt=0.0, le=50.0)
    zone_max_lateral_m: float = Field(1.5, gt=0.0, le=10.0)
    zone_max_heading_deg: float = Field(10.0, gt=0.0, le=45.0)
    # The launcher.
    front_board_width_m: float = Field(3.0, gt=0.0, le=20.0)
    side_board_length_m: float = Field(0.8, gt=0.0, le=10.0)
    side_board_sweep_deg: float = Field(45.0, ge=-90.0, le=90.0)
    cylinder_radius_m: float = Field(0.15, gt=0.0, le=2.0)
    cylinder_lateral_m: float = Field(2.5, gt=0.0, le=50.0)
    cylinder_ahead_m: float = Field(0.5, ge=-20.0, le=20.0)


class GeodeticOrigin(_Model):
    """The origin of the vehicle's local east-north frame (WGS84): near the routes."""

    lat_deg: float = Field(ge=-89.0, le=89.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    alt_m: float = Field(0.0, ge=-500.0, le=9000.0)


class Positioning(_Model):
    """What a GNSS/INS fix must show before automatic steering may use it, and where the
    antenna sits (from the vehicle's geometric centre: forward and to the left)."""

    origin: GeodeticOrigin | None = None
    max_fix_age_s: float = Field(0.5, gt=0.0, le=5.0)
    max_sigma_m: float = Field(0.15, gt=0.0, le=10.0)
    accepted_fix_qualities: tuple[Literal["gps", "dgps", "pps", "rtk_fixed", "rtk_float"], ...] = (
        "rtk_fixed",
        "rtk_float",
    )
    min_satellites: Annotated[int, Field(ge=0, le=64)] = 6
    antenna_forward_m: float = Field(0.0, ge=-20.0, le=20.0)
    antenna_left_m: float = Field(0.0, ge=-5.0, le=5.0)


class RouteFollowing(_Model):
    """The route autopilot (Stanley et al.): where routes are kept, which one is selected
    at start-up, and where engagement is allowed."""

    routes_dir: str | None = None  # None: <paths.state_dir>/routes
    selected: str | None = None  # a route name; `dbw route select` changes it at run time
    max_engage_distance_m: float = Field(10.0, gt=0.0, le=100.0)
    max_engage_heading_deg: float = Field(30.0, gt=0.0, le=90.0)
    lateral_accel_mps2: float = Field(1.0, gt=0.0, le=5.0)


class Supervision(_Model):
    """Restart policy shared by every supervised service unless the service overrides it."""

    restart_initial_backoff_s: float = Field(0.1, gt=0.0, le=10.0)
    restart_backoff_factor: float = Field(2.0, ge=1.0, le=10.0)
    restart_backoff_cap_s: float = Field(5.0, gt=0.0, le=300.0)
    max_restarts: Annotated[int, Field(ge=0, le=1000)] = 5
    # A service that has run this long without failing gets its restart budget back.
    restart_budget_reset_after_s: float = Field(30.0, gt=0.0, le=3600.0)
    control_heartbeat_deadline_s: float = Field(0.25, gt=0.0, le=5.0)
    cancel_timeout_s: float = Field(0.5, gt=0.0, le=10.0)

    @model_validator(mode="after")
    def _cap_not_below_initial(self) -> Self:
        if self.restart_backoff_cap_s < self.restart_initial_backoff_s:
            raise ValueError(
                "restart_backoff_cap_s must not be below restart_initial_backoff_s "
                f"(got {self.restart_backoff_cap_s} < {self.restart_initial_backoff_s})"
            )
        return self


class Kit(_Model):
    """The kit's installation on this vehicle, as far as its calibration depends on it."""

    # When the steering servo, its pot or their linkage were last mounted or changed: a
    # calibration whose steering was measured before then describes another installation,
    # and the daemon refuses it. None: not recorded (no such check).
    steering_installed_utc: AwareDatetime | None = None

    @field_validator("steering_installed_utc")
    @classmethod
    def _in_utc(cls, value: datetime | None) -> datetime | None:
        if value is not None and value.utcoffset() != UTC.utcoffset(None):
            raise ValueError(f"must be in UTC, ending in Z (got {value.isoformat()})")
        return value


class Paths(_Model):
    state_dir: str = Field("var/dbw", min_length=1)
    calibration_file: str = Field("var/dbw/calibration.toml", min_length=1)
    # The bench/status socket (`dbw status`, `dbw engage`, ...). Owned by the service
    # user, mode 0660: whoever can move the vehicle needs the socket's permissions.
    control_socket: str = Field("var/dbw/control.sock", min_length=1)


class SimPlacement(StrEnum):
    # The world and every twin in a child process the daemon starts and stops, reached
    # over TCP, ptys and SLCAN exactly as hardware: the daemon is measured as it runs on
    # a vehicle, and the simulation has a CPU budget of its own.
    PROCESS = "process"
    # Everything in the daemon's process and event loop: for tests and benchmarks that
    # reach into a twin (unplug a board, stall a telemetry stream, tap a pedal).
    INLINE = "inline"


class Recording(_Model):
    """The flight recorder (`appliance/recording/`): every input, sample and output to MCAP.

    On by default: after a field incident the recording is what can be replayed. It never
    holds up the control loop: a recorder that falls behind drops and counts, and on a
    filling disk it stops before the disk is full, never the vehicle.
    """

    enabled: bool = True
    directory: str | None = None  # None: <paths.state_dir>/recordings
    # A file is closed and the next one begun past either bound, so a file stays small
    # enough to copy off the vehicle and a crash costs at most one file's tail.
    split_size_mb: float = Field(256.0, gt=0.0, le=16384.0)
    split_duration_s: float = Field(600.0, gt=0.0, le=86400.0)
    # The oldest closed files are deleted while the directory holds more than this.
    quota_mb: float = Field(8192.0, gt=0.0)
    # Free space on the recording's file system: below warn a warning, below stop the
    # recorder stops writing (and resumes above warn).
    warn_free_mb: float = Field(2048.0, ge=0.0)
    stop_free_mb: float = Field(512.0, ge=0.0)
    # A chunk is finished and written at least this often, so a crash loses no more.
    flush_interval_s: float = Field(1.0, gt=0.0, le=60.0)
    # What the daemon may hold for a recorder that falls behind before it drops.
    max_backlog_mb: float = Field(16.0, gt=0.0, le=1024.0)

    @model_validator(mode="after")
    def _thresholds(self) -> Self:
        if self.stop_free_mb > self.warn_free_mb:
            raise ValueError("stop_free_mb must not be above warn_free_mb")
        return self


class SystemMonitor(_Model):
    """The PC's own health (Stanley et al.'s memory/storage and system monitors): load,
    memory, free disk, temperature where readable, wall-clock jumps; probed off the
    control loop. Below the stop levels it is a fault the safety layer acts on."""

    enabled: bool = True
    period_s: float = Field(1.0, ge=0.1, le=60.0)
    # A probe still running after this is logged as stuck; its sample then ages, and past
    # max_age_s the monitor counts as not reporting: a fault while engaged.
    probe_timeout_s: float = Field(2.0, gt=0.0, le=60.0)
    max_age_s: float = Field(5.0, gt=0.0, le=600.0)
    disk_path: str | None = None  # None: paths.state_dir (logs, recordings, calibration)
    disk_warn_free_mb: float = Field(1024.0, ge=0.0)
    disk_stop_free_mb: float = Field(256.0, ge=0.0)
    temperature_warn_c: float = Field(80.0, ge=0.0, le=150.0)
    temperature_max_c: float = Field(95.0, ge=0.0, le=150.0)
    memory_min_available_mb: float = Field(128.0, ge=0.0)
    # A wall-clock step bigger than this between two probes is logged (wall_clock_jump).
    clock_jump_warn_s: float = Field(0.5, gt=0.0)

    @model_validator(mode="after")
    def _levels(self) -> Self:
        if self.disk_stop_free_mb > self.disk_warn_free_mb:
            raise ValueError("disk_stop_free_mb must not be above disk_warn_free_mb")
        if self.temperature_warn_c > self.temperature_max_c:
            raise ValueError("temperature_warn_c must not be above temperature_max_c")
        if self.max_age_s < 2 * self.period_s:
            raise ValueError("max_age_s must be at least two periods (period_s)")
        return self


class LiveView(_Model):
    """The Foxglove WebSocket live view (appliance/live_view.py): off by default; on the
    loopback address unless allow_non_loopback says this vehicle serves other machines."""

    enabled: bool = False
    host: str = Field("127.0.0.1", min_length=1)
    port: Port = 8765
    allow_non_loopback: bool = False
    # Per topic, while someone watches: bounds what the live view costs the event loop.
    max_rate_hz: float = Field(10.0, gt=0.0, le=100.0)


class OperatorPageSettings(_Model):
    """The operator page (`appliance/operator_page/`): a read-only view of the daemon in a
    browser (mode, reasons, faults, input ages, docking or route view, the last scans).

    Off by default. It listens on loopback only; a vehicle whose operator screen is another
    machine must say so with allow_non_loopback (there is no authentication: the network it
    then listens on is the only protection).
    """

    enabled: bool = False
    host: str = Field("127.0.0.1", min_length=1, max_length=255)
    port: Port = 8080
    allow_non_loopback: bool = False

    @model_validator(mode="after")
    def _loopback_unless_allowed(self) -> Self:
        if self.allow_non_loopback or self.host.lower() == "localhost":
            return self
        try:
            loopback = ipaddress.ip_address(self.host.strip("[]")).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(
                f"operator_page.host {self.host!r} is not a loopback address: use 127.0.0.1, "
                "or set operator_page.allow_non_loopback = true to listen beyond this PC"
            )
        return self


class SimSteering(_Model):
    """The simulated steering's installation: what a calibration measures and must not
    be told. The built-in simulated calibration assumes the defaults, so changing these
    gives a daemon whose calibration is off, as on a vehicle whose pot was remounted."""

    pot_centre_counts: float = Field(2131.0, ge=500.0, le=3600.0)
    # The servo's relative encoder reads this much less than the wheel's angle.
    encoder_offset_rad: float = Field(0.0, ge=-100.0, le=100.0)
    pot_seed: int = Field(0, ge=0, le=2**32 - 1)
    # The linkage's departure from the constant steering ratio at the lock (the palm tree
    # measures it): tyre = wheel / ratio * (1 + linkage_cubic * (wheel / lock)**2).
    linkage_cubic: float = Field(0.0, ge=-0.3, le=0.3)
    # The true rear/front counter-steer ratio; None: the vehicle file's geometry value.
    counter_steer_ratio_k: float | None = Field(None, ge=0.0, le=1.0)
    # Steering-wheel rad per tyre rad. The simulated wheel turns 1.5 turns each way, so
    # 18 locks the tyres at 30 deg (a car), 9 at 60 deg (a forklift's rear axle).
    steering_ratio: float = Field(18.0, ge=4.0, le=40.0)


class Simulation(_Model):
    """The built-in simulated vehicle: the world and the twins of every device."""

    enabled: bool = True
    placement: SimPlacement = SimPlacement.PROCESS
    world_step_hz: float = Field(100.0, ge=10.0, le=1000.0)
    # A built-in site (launcher, pallets) or a site TOML file the simulated scanners see.
    site: str = Field("launcher", min_length=1)
    # Where the vehicle starts: Qian et al. bring it "in front of the launcher at a
    # distance of about 10 m and with a small heading angle".
    start_x_m: float = Field(-12.6, ge=-1000.0, le=1000.0)
    start_y_m: float = Field(0.4, ge=-1000.0, le=1000.0)
    start_yaw_deg: float = Field(3.0, ge=-180.0, le=180.0)
    # What the simulated LMS111s get wrong (appliance/sim/scanner_errors.py): "realistic"
    # gives each the data sheet's noise and systematic error, the beam footprint that mixes
    # ranges at edges, the remission it needs at each range, and a mount a few millimetres
    # and tenths of a degree off the configured one; "ideal" measures exact geometry.
    scanner_model: Literal["realistic", "ideal"] = "realistic"
    # Draws each scanner's systematic and mount errors (one vehicle per seed), and its noise.
    scanner_seed: int = Field(1, ge=0, le=2**32 - 1)
    steering: SimSteering = SimSteering()
    pedals: SimPedals = SimPedals()
    # The simulated GNSS/INS receiver's white position noise per horizontal axis (what
    # its GST reports): 5 cm, a clean RTK receiver; the calibration figures use 2 cm.
    gnss_sigma_m: float = Field(0.05, ge=0.0, le=10.0)


class VehicleConfig(_Model):
    """The whole configuration of one vehicle, as loaded from one TOML file."""

    name: str = Field("sim", min_length=1, max_length=64)
    kind: VehicleKind = VehicleKind.FOUR_WHEEL_COUNTER_STEER
    geometry: Geometry = Geometry()
    limits: Limits = Limits()
    devices: Devices = Devices()
    rates: Rates = Rates()
    staleness: Staleness = Staleness()
    safety: SafetyTimeouts = SafetyTimeouts()
    engagement: Engagement = Engagement()
    docking: Docking = Docking()
    positioning: Positioning = Positioning()
    route: RouteFollowing = RouteFollowing()
    pedal_sweep: PedalSweepSettings = PedalSweepSettings()
    lookahead_tuning: LookaheadTuningSettings = LookaheadTuningSettings()
    palm_tree_drive: PalmTreeDriveSettings = PalmTreeDriveSettings()
    # A forklift's (kind = "forklift"): where its forks are, how it approaches a pallet.
    forks: Forks = Forks()
    pallets: PalletGuidanceSettings = PalletGuidanceSettings()
    tablet_page: TabletPageSettings = TabletPageSettings()
    # How speed is commanded: "pc104" sends a speed set-point to the vehicle's own PC104
    # (the flat-bed); "pedals" closes the speed loop here on the throttle and brake
    # actuators (the Husky, whose engine throttle was its autopilot's speed control).
    speed_path: Literal["pc104", "pedals"] = "pc104"
    supervision: Supervision = Supervision()
    paths: Paths = Paths()
    kit: Kit = Kit()
    recording: Recording = Recording()
    system_monitor: SystemMonitor = SystemMonitor()
    live_view: LiveView = LiveView()
    operator_page: OperatorPageSettings = OperatorPageSettings()
    simulation: Simulation = Simulation(enabled=False)

    def _linkage_within_the_steering_limit(self) -> None:
        """The simulated linkage must not turn the tyre past the vehicle's steering limit
        at the wheel's lock: the simulated vehicle clamps its tyres there, so the linkage
        a calibration measured would not be the one configured."""
        servo = ServoParams(steering_ratio=self.simulation.steering.steering_ratio)
        cubic = self.simulation.steering.linkage_cubic
        lock_deg = math.degrees(servo.wheel_limit_rad / servo.steering_ratio * (1.0 + cubic))
        if lock_deg > self.limits.max_steer_angle_deg:
            raise ValueError(
                f"simulation.steering.linkage_cubic = {cubic} turns the simulated tyre to "
                f"{lock_deg:.1f} deg at the wheel's lock, past limits.max_steer_angle_deg "
                f"({self.limits.max_steer_angle_deg} deg): lower it"
            )

    @model_validator(mode="after")
    def _cross_checks(self) -> Self:
        if not self.simulation.enabled:
            for field_name in (
                "steering_serial",
                "throttle_serial",
                "brake_serial",
                "panel_serial",
            ):
                endpoint: SerialEndpoint = getattr(self.devices, field_name)
                if endpoint.port.startswith(SIM_PORT_PREFIX):
                    raise ValueError(
                        f"devices.{field_name}.port is {endpoint.port!r}, a simulated board, "
                        "but simulation.enabled is false: set the real serial device "
                        "(e.g. /dev/ttyUSB0) or enable the simulation"
                    )
            gnss = self.devices.gnss
            if gnss is not None and gnss.port.startswith(SIM_PORT_PREFIX):
                raise ValueError(
                    f"devices.gnss.port is {gnss.port!r}, the simulated receiver, but "
                    "simulation.enabled is false: set the receiver's serial device "
                    "(e.g. /dev/serial/by-id/...) or enable the simulation"
                )
        if self.simulation.enabled and self.simulation.steering.linkage_cubic != 0.0:
            self._linkage_within_the_steering_limit()
        if self.engagement.max_set_speed_mps > self.limits.max_speed_mps:
            raise ValueError(
                "engagement.max_set_speed_mps must not exceed limits.max_speed_mps "
                f"(got {self.engagement.max_set_speed_mps} > {self.limits.max_speed_mps})"
            )
        engagement = self.engagement
        if engagement.hold_to_move:
            # The controlled stop aims at 70 % of the distance (the PC104's speed loop lags).
            needed = engagement.max_set_speed_mps**2 / (
                2.0 * engagement.hold_to_move_stop_distance_m * 0.7
            )
            if needed > self.safety.full_brake_decel_mps2:
                raise ValueError(
                    "engagement.hold_to_move_stop_distance_m is too short to stop from "
                    f"max_set_speed_mps={engagement.max_set_speed_mps}: it needs "
                    f"{needed:.1f} m/s^2, more than safety.full_brake_decel_mps2="
                    f"{self.safety.full_brake_decel_mps2}"
                )
        if engagement.autopilot_source == "route":
            if self.devices.gnss is None:
                raise ValueError(
                    'engagement.autopilot_source = "route" needs a position receiver: '
                    "set [devices.gnss] (port, receiver_latency_s)"
                )
            if self.positioning.origin is None:
                raise ValueError(
                    'engagement.autopilot_source = "route" needs the local frame\'s origin: '
                    "set [positioning.origin] (lat_deg, lon_deg) near the routes"
                )
        if engagement.autopilot_source == "pallet":
            problems = []
            if self.kind is not VehicleKind.FORKLIFT:
                problems.append(f'kind = "forklift" (not "{self.kind}")')
            if not self.pallets.landmarks:
                problems.append("[[pallets.landmarks]]: the posts the forklift localizes on")
            if not self.pallets.worker_map:
                problems.append("pallets.worker_map: the worker's map to merge")
            if problems:
                raise ValueError(
                    'engagement.autopilot_source = "pallet" needs ' + "; ".join(problems)
                )
        # Compared with the default, not "was it set": a config written back out (the sim
        # child's copy) carries the default CAN section and must load again.
        if self.speed_path == "pedals" and self.devices.can != CanEndpoint():
            raise ValueError(
                'speed_path = "pedals" drives the throttle and brake actuators and uses no '
                "PC104: remove [devices.can] (a vehicle without a PC104 has no CAN link)"
            )
        if self.speed_path == "pedals" and self.pedal_sweep != PedalSweepSettings():
            # A sweep of the file's own is checked now; the defaults only when a sweep is
            # armed (a vehicle that never sweeps must not fail to load over them, nor
            # its copy written out for the simulator's process).
            problems = sweep_limit_problems(self.pedal_sweep, self.limits, self.engagement)
            if problems:
                raise ValueError("; ".join(problems))
        if self.tablet_page.enabled and not engagement.hold_to_move:
            raise ValueError(
                "tablet_page.enabled needs engagement.hold_to_move = true: the tablet's "
                "button is hold-to-move's, and a vehicle without it has none to hold"
            )
        if self.palm_tree_drive.allowed:
            problems = palm_tree_drive_problems(self.palm_tree_drive, self.limits, self.engagement)
            if problems:
                raise ValueError("; ".join(problems))
        control_period_s = 1.0 / self.rates.control_hz
        if self.supervision.control_heartbeat_deadline_s < 2 * control_period_s:
            raise ValueError(
                "supervision.control_heartbeat_deadline_s must be at least two control periods "
                f"({2 * control_period_s:.3f} s at rates.control_hz={self.rates.control_hz})"
            )
        if self.staleness.pc104_status_max_age_s < control_period_s:
            raise ValueError(
                "staleness.pc104_status_max_age_s must be at least one control period "
                f"({control_period_s:.3f} s)"
            )
        return self
