"""The simulated PC104, driven frame by frame with a fake clock (no bus, no asyncio)."""

from __future__ import annotations

from appliance.config import load_config
from appliance.sim.twins.pc104_core import OutFrame, Pc104TwinCore, PidSpeedController, TwinFaults
from appliance.sim.vehicle import VehicleParams
from appliance.sim.world import SimWorld
from drivers.pc104 import protocol
from drivers.pc104.errorframes import BusCondition, bus_condition
from drivers.pc104.messages import (
    ControlSource,
    MotionCommand,
    MotionPattern,
    Pc104Status,
    WheelAngles,
)

TICK_S = 0.005
STATUS_ID = protocol.spec_for(Pc104Status).frame_id


class Bench:
    """A twin core, its world and a fake high level sending commands every 20 ms."""

    def __init__(self, **core_kwargs: object) -> None:
        self.world = SimWorld(VehicleParams.from_config(load_config("sim")))
        self.core = Pc104TwinCore(self.world, **core_kwargs)  # type: ignore[arg-type]
        self.t_s = 0.0
        self.counter = 0
        self.frames: list[tuple[float, OutFrame]] = []

    def run(self, seconds: float, command: MotionCommand | None) -> None:
        end_s = self.t_s + seconds
        next_command_s = self.t_s
        while self.t_s < end_s - 1e-9:
            self.t_s += TICK_S
            if command is not None and self.t_s >= next_command_s - 1e-9:
                self.core.on_frame(*protocol.encode(command, self.counter), self.t_s)
                self.counter = (self.counter + 1) % 16
                next_command_s += 0.02
            self.world.advance_to(self.t_s)
            self.frames.extend((self.t_s, f) for f in self.core.tick(self.t_s))

    def last(self, message_type: type) -> protocol.DecodedFrame:
        frame_id = protocol.spec_for(message_type).frame_id
        frame = next(f for _, f in reversed(self.frames) if f.arbitration_id == frame_id)
        return protocol.decode(frame.arbitration_id, frame.data, self.t_s)

    def status(self) -> Pc104Status:
        message = self.last(Pc104Status).message
        assert isinstance(message, Pc104Status)
        return message


STOP = MotionCommand.stop()
FORWARD = MotionCommand(MotionPattern.STRAIGHT, 1.0)


def test_it_reports_at_the_dbc_periods() -> None:
    bench = Bench()
    bench.run(1.0, STOP)
    ids = [f.arbitration_id for _, f in bench.frames]
    for spec in protocol.SPECS.values():
        if spec.frame_id in protocol.PC104_IDS:
            assert abs(ids.count(spec.frame_id) - 1.0 / spec.period_s) <= 1, spec.name


def test_it_waits_for_stop_then_follows_the_speed_setpoint() -> None:
    bench = Bench()
    bench.run(0.5, FORWARD)
    assert bench.world.state.speed_mps == 0.0
    assert bench.status().stop_required and not bench.status().ready
    bench.run(0.1, STOP)
    assert bench.status().ready
    bench.run(4.0, FORWARD)
    assert abs(bench.world.state.speed_mps - 1.0) < 0.1
    assert bench.status().active_pattern is MotionPattern.STRAIGHT
    assert abs(bench.status().measured_speed_mps - bench.world.state.speed_mps) < 0.05


def test_it_stops_the_vehicle_100_ms_after_commands_stop() -> None:
    bench = Bench()
    bench.run(0.1, STOP)
    bench.run(3.0, FORWARD)
    moving_mps = bench.world.state.speed_mps
    assert moving_mps > 0.5
    bench.run(0.1, None)
    assert bench.world.command.brake_pct < 100.0  # 100 ms: not yet
    bench.run(0.015, None)
    assert bench.world.command.pattern is MotionPattern.STOP
    assert bench.world.command.brake_pct == 100.0
    bench.run(1.0, None)
    assert bench.world.state.speed_mps == 0.0
    status = bench.status()
    assert status.faults.command_timeout and status.stop_required
    bench.run(0.5, FORWARD)  # commands resume, but motion needs a STOP first
    assert bench.world.state.speed_mps == 0.0


def test_bad_commands_are_ignored_and_counted() -> None:
    bench = Bench()
    bench.run(0.1, STOP)
    arbitration_id, data = protocol.encode(FORWARD, bench.counter)
    bench.core.on_frame(arbitration_id, data[:-1] + bytes([data[-1] ^ 1]), bench.t_s)
    bench.core.on_frame(arbitration_id, data[:3], bench.t_s)
    bench.run(0.02, None)
    status = bench.status()
    assert status.bad_command_frames == 2
    assert status.faults.command_invalid
    assert status.active_pattern is MotionPattern.STOP


def test_cab_takeover_ignores_the_high_level() -> None:
    bench = Bench()
    bench.run(0.1, STOP)
    bench.core.faults.cab_control = True
    bench.run(0.5, FORWARD)
    status = bench.status()
    assert status.control_source is ControlSource.CAB and not status.ready
    assert "pc104" not in bench.world._inputs
    bench.core.faults.cab_control = False
    bench.run(0.1, FORWARD)
    assert bench.status().stop_required


def test_wheel_rows_interpolate_front_to_rear() -> None:
    bench = Bench()
    bench.run(0.1, STOP)
    bench.run(2.0, MotionCommand(MotionPattern.COUNTER_STEER, 0.5, front_steer_rad=0.2))
    wheels = bench.last(WheelAngles).message
    assert isinstance(wheels, WheelAngles)
    front, rear = wheels.row_angles_rad[0], wheels.row_angles_rad[3]
    assert front > 0.15 and rear < -0.05  # counter-steer: rear wheels turned right
    assert front > wheels.row_angles_rad[1] > wheels.row_angles_rad[2] > rear


def test_faults_shape_what_goes_out() -> None:
    bench = Bench()
    bench.run(0.2, STOP)
    bench.core.faults.bad_crc = True
    bench.frames.clear()
    bench.run(0.1, STOP)
    for _, frame in bench.frames:
        data = frame.data
        assert data[-1] != protocol.frame_crc(frame.arbitration_id, data[:-1])
    bench.core.faults.bad_crc = False
    bench.core.faults.stuck_counter = True
    bench.frames.clear()
    bench.run(0.1, STOP)
    counters = {f.data[0] >> 4 for _, f in bench.frames if f.arbitration_id == STATUS_ID}
    assert len(counters) == 1
    bench.core.faults.stuck_counter = False
    bench.core.faults.drop_all = True
    bench.frames.clear()
    bench.run(0.1, STOP)
    assert bench.frames == []
    bench.core.faults.drop_all = False
    bench.core.faults.delay_s = 0.05
    bench.frames.clear()
    bench.run(0.045, STOP)  # the first frame is built within 20 ms, sent 50 ms later
    assert bench.frames == []
    bench.run(0.03, STOP)
    assert bench.frames


def test_bus_off_goes_silent_and_announces_itself_on_a_virtual_bus() -> None:
    bench = Bench(faults=TwinFaults(), emit_error_frames=True)
    bench.run(0.1, STOP)
    bench.core.faults.bus_off = True
    bench.frames.clear()
    bench.run(0.3, FORWARD)
    assert [f.is_error_frame for _, f in bench.frames] == [True]
    error = bench.frames[0][1]
    assert bus_condition(error.arbitration_id, error.data) is BusCondition.BUS_OFF
    assert bench.world.command.pattern is MotionPattern.STOP  # commands unheard: stopped
    bench.core.faults.bus_off = False
    bench.frames.clear()
    bench.run(0.05, STOP)
    first = bench.frames[0][1]
    assert first.is_error_frame
    assert bus_condition(first.arbitration_id, first.data) is BusCondition.ACTIVE


def test_restart_counts_from_zero_and_requires_stop() -> None:
    bench = Bench()
    bench.run(0.1, STOP)
    bench.run(1.0, FORWARD)
    bench.core.restart(bench.t_s)
    bench.frames.clear()
    bench.run(0.01, FORWARD)
    assert bench.last(Pc104Status).counter == 0
    assert bench.status().stop_required


def test_pid_brakes_before_reversing_and_holds_at_zero() -> None:
    pid = PidSpeedController()
    assert pid.update(-1.0, 0.5, 0.01) == (0.0, 100.0, True)
    assert pid.update(0.0, 0.0, 0.01) == (0.0, 100.0, False)
    throttle, brake, reverse = pid.update(1.0, 0.0, 0.01)
    assert throttle > 0 and brake == 0 and not reverse
    throttle, brake, _ = pid.update(1.0, 2.0, 0.01)
    assert throttle == 0 and brake > 0
