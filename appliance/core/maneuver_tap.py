"""The calibration maneuvers' tap: what each control cycle saw, kept while a maneuver runs.

Why in the core: a maneuver's fit needs the raw readings of every cycle (the pot's counts,
the servo's encoder and torque, the GNSS/INS epoch, the speed, the pedals) together with
what the core made of them (mode, stale inputs, faults, the commands it sent). Polling
`dbw status` would miss cycles and pair readings from different ones; the core has them
all in one place once per cycle. The tap only reads: it never changes a command, so a
maneuver cannot move the vehicle by being tapped.

Why it is started and stopped by a request: a request is told to the recorder like the
bench's, so replaying a recording re-runs the same tap over the same cycles and gives the
same samples (``dbw calibrate fit RECORDING``). The client (``dbw calibrate STEP``) reads
the samples through the control socket, from a bounded ring: a client that falls behind
loses the oldest samples and is told how many, never stalls the loop.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from dataclasses import asdict, dataclass
from typing import Any, Final

from appliance.core.inputs import ControlInputs
from appliance.core.observe import Measurements
from appliance.core.output import CoreOutput
from appliance.guidance.palm_tree_drive import DriveCommand
from appliance.guidance.pedal_sweep import SweepCommand
from appliance.localization.gnss_pose import GnssPose
from drivers.actuators.messages import SteeringMode

STEPS: Final = ("pot-center", "pot-map", "palm-tree", "k-ratio", "lookahead", "pedals")
# Ten minutes at the 50 Hz control rate: longer than any client pause, small in memory.
RING_SAMPLES: Final = 30_000
MAX_SAMPLES_PER_REPLY: Final = 500


@dataclass(frozen=True, slots=True)
class ManeuverSample:
    """One control cycle as a maneuver's fit sees it. None: not fresh, not known."""

    seq: int
    t_s: float
    mode: str
    engaged: bool
    stale: tuple[str, ...]
    faults: tuple[str, ...]
    pot_counts: int | None  # raw, uncalibrated: the pot map is what is being measured
    servo_position_rad: float | None  # the servo's relative encoder, steering-wheel side
    servo_torque_nm: float | None
    steer_setpoint_rad: float | None  # servo frame; None: the servo is released
    steer_wheel_rad: float | None  # through the current calibration, where there is one
    speed_mps: float | None
    throttle_actuator_pct: float | None
    brake_actuator_pct: float | None
    throttle_command_pct: float | None  # None: released
    brake_command_pct: float | None
    gnss_time_s: float | None  # the epoch's measurement time (core clock)
    east_m: float | None
    north_m: float | None
    yaw_rad: float | None
    yaw_rate_rad_per_s: float | None
    gnss_speed_mps: float | None
    sigma_m: float | None
    fix_quality: str | None
    # The pedal sweep's phase and run (0-based), while it is armed; None otherwise.
    sweep_phase: str | None = None
    sweep_run: int | None = None
    # The look-ahead runs' phase and run (0-based) while armed, the anchor's cross-track
    # error against the run's course (left positive) and the look-ahead the tracker used.
    tune_phase: str | None = None
    tune_run: int | None = None
    cross_track_m: float | None = None
    lookahead_m: float | None = None
    # The palm tree driven by the daemon: its phase and arc (0-based) while armed.
    palm_phase: str | None = None
    palm_arc: int | None = None

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


SampleListener = Callable[[ManeuverSample], None]


def _finite(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def make_sample(
    seq: int,
    inputs: ControlInputs,
    fresh: frozenset[str],
    measured: Measurements,
    output: CoreOutput,
    stale: Iterable[str],
    faults: Iterable[str],
    sweep: SweepCommand | None = None,
    tuning: Mapping[str, Any] | None = None,
    palm: DriveCommand | None = None,
) -> ManeuverSample:
    """One cycle's sample: raw readings where fresh, and what the core commanded."""
    steering = inputs.steering if "steering.pot" in fresh else None
    throttle = inputs.throttle if "board.throttle" in fresh else None
    brake = inputs.brake if "board.brake" in fresh else None
    gnss = inputs.gnss if isinstance(inputs.gnss, GnssPose) else None
    servo = output.steering
    return ManeuverSample(
        seq=seq,
        t_s=output.now_s,
        mode=str(output.mode),
        engaged=output.engaged,
        stale=tuple(stale),
        faults=tuple(faults),
        pot_counts=None if steering is None else steering.pot_raw_counts,
        servo_position_rad=measured.servo_position_rad,
        servo_torque_nm=None if steering is None else measured.servo_torque_nm,
        steer_setpoint_rad=None
        if servo.mode is SteeringMode.RELEASE
        else servo.wheel_angle_setpoint_rad,
        steer_wheel_rad=measured.steer_wheel_rad,
        speed_mps=measured.speed_mps,
        throttle_actuator_pct=None if throttle is None else throttle.actuator_position_pct,
        brake_actuator_pct=None if brake is None else brake.actuator_position_pct,
        throttle_command_pct=output.throttle.position_pct if output.throttle.enable else None,
        brake_command_pct=output.brake.position_pct if output.brake.enable else None,
        gnss_time_s=None if gnss is None else gnss.measurement_time_s,
        east_m=None if gnss is None else gnss.east_m,
        north_m=None if gnss is None else gnss.north_m,
        yaw_rad=None if gnss is None else _finite(gnss.yaw_rad),
        yaw_rate_rad_per_s=None if gnss is None else _finite(gnss.yaw_rate_rad_per_s),
        gnss_speed_mps=None if gnss is None else _finite(gnss.speed_mps),
        sigma_m=None if gnss is None else _finite(gnss.sigma_worst_m),
        fix_quality=None if gnss is None else str(gnss.quality),
        sweep_phase=None if sweep is None else str(sweep.phase),
        sweep_run=None if sweep is None else sweep.run,
        tune_phase=None if tuning is None else _text(tuning.get("phase")),
        tune_run=None if tuning is None else _integer(tuning.get("run")),
        cross_track_m=None if tuning is None else _number(tuning.get("cross_track_m")),
        lookahead_m=None if tuning is None else _number(tuning.get("lookahead_m")),
        palm_phase=None if palm is None else str(palm.phase),
        palm_arc=None if palm is None else palm.arc,
    )


def _text(value: object) -> str | None:
    return value if isinstance(value, str) else None


def _integer(value: object) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


def _number(value: object) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return _finite(float(value))


class ManeuverTap:
    """Which maneuver is being tapped, and the ring of its samples (reset()/update())."""

    def __init__(self, ring_samples: int = RING_SAMPLES) -> None:
        if ring_samples < 1:
            raise ValueError(f"ring_samples must be at least 1 (got {ring_samples})")
        self.ring_samples = ring_samples
        # Told of every sample (replay collects a whole maneuver this way, past the ring).
        self.listeners: list[SampleListener] = []
        self.reset()

    def reset(self) -> None:
        self.step: str | None = None
        self.started_s: float | None = None
        self.stopped_s: float | None = None
        self.next_seq = 0
        self.first_seq = 0  # the running (or last) maneuver's first sample
        self._ring: deque[ManeuverSample] = deque(maxlen=self.ring_samples)

    @property
    def active(self) -> bool:
        return self.step is not None and self.stopped_s is None

    def start(self, step: str, now_s: float) -> tuple[bool, str]:
        """Tap from the next cycle on. Sequence numbers go on across maneuvers, so a
        client can never mistake an earlier maneuver's samples for this one's."""
        if step not in STEPS:
            return False, f"unknown maneuver {step!r}; known: {', '.join(STEPS)}"
        if self.active:
            return False, f"maneuver {self.step!r} is running: stop it first"
        self.step, self.started_s, self.stopped_s = step, now_s, None
        self.first_seq = self.next_seq
        self._ring.clear()
        return True, f"tapping {step} from sample {self.next_seq}"

    def stop(self, now_s: float) -> tuple[bool, str]:
        if not self.active:
            return False, "no maneuver is running"
        self.stopped_s = now_s
        return True, f"{self.step} stopped after sample {self.next_seq - 1}"

    def update(
        self,
        inputs: ControlInputs,
        fresh: frozenset[str],
        measured: Measurements,
        output: CoreOutput,
        stale: Iterable[str],
        faults: Iterable[str],
        sweep: SweepCommand | None = None,
        tuning: Mapping[str, Any] | None = None,
        palm: DriveCommand | None = None,
    ) -> None:
        if not self.active:
            return
        sample = make_sample(
            self.next_seq, inputs, fresh, measured, output, stale, faults, sweep, tuning, palm
        )
        self.next_seq += 1
        self._ring.append(sample)
        for listener in self.listeners:
            listener(sample)

    def samples_since(self, seq: int, limit: int = MAX_SAMPLES_PER_REPLY) -> dict[str, Any]:
        """Samples with ``seq`` or later (at most ``limit``), and how many of those the
        ring no longer holds (``missed``): the client knows exactly what it lost."""
        ring = self._ring
        first = ring[0].seq if ring else self.next_seq
        start = max(seq, first)
        missed = max(0, min(first, self.next_seq) - max(seq, 0)) if seq < first else 0
        offset = start - first
        chunk = [ring[i].as_dict() for i in range(offset, min(len(ring), offset + limit))]
        return {
            "step": self.step,
            "active": self.active,
            "samples": chunk,
            "next": start + len(chunk),
            "missed": missed,
        }

    def status(self) -> Mapping[str, Any] | None:
        if self.step is None:
            return None
        return {
            "step": self.step,
            "active": self.active,
            "started_s": self.started_s,
            "stopped_s": self.stopped_s,
            "first_seq": self.first_seq,
            "samples": self.next_seq - self.first_seq,
        }
