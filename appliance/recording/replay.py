"""Deterministic replay: the recorded inputs through the same core, the outputs compared.

The core is pure (`ControlCore.step(inputs, now_s)`: no clock, no randomness, no I/O),
so the same code given the same inputs at the same times in the same order must make
the same outputs, to the bit. Replay rebuilds the core from the vehicle file and the
calibration the recording carries, then walks the messages in the order the daemon made
them: a core restart resets the core, a control-socket request is put to it between
the same two cycles, and each cycle's inputs (its scans taken from the scan samples by
seq) are stepped at the recorded ``now_s``. Perception, localization and guidance run
inside the step, so they are replayed too. Each replayed output is compared with the
recorded one: first as the bytes the recorder would have written for it (the same bytes
are the same output, and nothing of the recorded one need be decoded), then, where the
bytes differ, field by field, as openpilot's process replay does; the first divergence
names the time, the field, and both values. A tolerance per field (a path pattern) is
for comparing across code versions on purpose; the default is exact.
"""

from __future__ import annotations

import fnmatch
import json
import math
from collections.abc import Callable, Iterable, Iterator, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from appliance.config import VehicleConfig
from appliance.config.calibration import Calibration
from appliance.config.calibration_file import CalibrationError, parse_calibration
from appliance.config.loader import ConfigError, parse_config
from appliance.core.core import ControlCore
from appliance.core.inputs import ControlInputs
from appliance.core.output import CoreOutput
from appliance.core.pallet_autopilot import PalletAutopilot
from appliance.mapping.pallets import Pallet, PalletMap
from appliance.recording.channels import (
    CYCLE_TOPIC,
    REQUEST_TOPIC,
    RESET_TOPIC,
    SAMPLE_TOPIC_PREFIX,
    cycle_ending,
)
from appliance.recording.codec import CodecError
from appliance.recording.fastcodec import encode_fast
from appliance.recording.fastdecode import decode_fast as decode
from appliance.recording.reader import RecordedMessage, RecordingReader
from drivers.lms111.mounted import MountedScan

# Scan samples kept per side: a cycle sees the newest or one just before it.
SCANS_KEPT = 16


class ReplayError(Exception):
    """A recording replay cannot start or go on with (no config, a broken message)."""


@dataclass(frozen=True)
class Divergence:
    log_time_ns: int
    now_s: float
    topic: str
    field: str
    recorded: Any
    replayed: Any

    def describe(self, start_ns: int) -> str:
        at = (self.log_time_ns - start_ns) / 1e9
        recorded = json.dumps(self.recorded)[:120]
        replayed = json.dumps(self.replayed)[:120]
        return (
            f"t={at:.3f} s (now_s {self.now_s:.6f}) {self.topic} {self.field}: "
            f"recorded {recorded}, replayed {replayed}"
        )


@dataclass
class ReplayResult:
    cycles: int = 0
    cycles_skipped: int = 0  # before the recording's first core start: no state to step
    requests: int = 0
    resets: int = 0
    divergent_cycles: int = 0
    divergences: list[Divergence] = field(default_factory=list)  # the first few
    first_log_time_ns: int | None = None
    last_log_time_ns: int | None = None

    @property
    def matched(self) -> bool:
        return self.divergent_cycles == 0 and self.cycles > 0

    @property
    def duration_s(self) -> float:
        if self.first_log_time_ns is None or self.last_log_time_ns is None:
            return 0.0
        return (self.last_log_time_ns - self.first_log_time_ns) / 1e9


@dataclass(frozen=True)
class Tolerance:
    pattern: str  # fnmatch over the dotted field path, e.g. "output.pc104_pose.*"
    abs_tol: float

    @classmethod
    def parse(cls, text: str) -> Tolerance:
        pattern, sep, value = text.partition("=")
        try:
            tol = float(value)
        except ValueError:
            tol = math.nan
        if not sep or not pattern or not math.isfinite(tol) or tol < 0:
            raise ValueError(f"tolerance {text!r}: expected FIELD_PATTERN=NON_NEGATIVE_NUMBER")
        return cls(pattern, tol)


def core_from_metadata(metadata: Mapping[str, Mapping[str, str]]) -> ControlCore:
    """The core the recording's daemon ran: its vehicle file and calibration."""
    config_text = metadata.get("dbw.config", {}).get("toml")
    if not config_text:
        raise ReplayError("the recording has no vehicle file (metadata dbw.config)")
    try:
        config = parse_config(config_text, source="<recorded vehicle file>")
    except ConfigError as exc:
        raise ReplayError(f"the recorded vehicle file does not load here: {exc}") from exc
    calibration_meta = metadata.get("dbw.calibration", {})
    calibration = _calibration(config, calibration_meta.get("toml", ""))
    autopilot = None
    worker_meta = metadata.get(WORKER_MAP_METADATA)
    if worker_meta is not None and config.engagement.autopilot_source == "pallet":
        worker = _recorded_worker(worker_meta, "json", PalletMap, None)
        problem = str(worker_meta.get("problem", "")) or "no worker map was recorded"
        alternatives = _recorded_worker(worker_meta, "alternatives_json", tuple[Pallet, ...], ())
        autopilot = PalletAutopilot(
            config,
            calibration,
            worker=worker,
            worker_problem="" if worker else problem,
            worker_alternatives=alternatives,
        )
    return ControlCore(config, calibration, calibration_meta.get("problem", ""), autopilot)


WORKER_MAP_METADATA = "dbw.worker_map"


def _recorded_worker(meta: Mapping[str, str], key: str, kind: Any, absent: Any) -> Any:
    """One part of the recorded worker's map (``absent`` when it was not recorded)."""
    if not meta.get(key):
        return absent
    try:
        return decode(json.loads(meta[key]), kind)
    except (CodecError, ValueError) as exc:
        raise ReplayError(f"the recorded worker's map does not load: {exc}") from exc


def worker_map_metadata(source: PalletAutopilot) -> dict[str, dict[str, str]]:
    """The `pallet` source's worker map for the recording's metadata (the map the file
    held, or none and why), so a replay is the recorded run without the file."""
    worker = source.worker
    return {
        WORKER_MAP_METADATA: {
            "json": "" if worker is None else json.dumps(encode_fast(worker, PalletMap)),
            "alternatives_json": json.dumps(
                encode_fast(source.worker_alternatives, tuple[Pallet, ...])
            ),
            "source": source.config.pallets.worker_map,
            "problem": source.worker_problem,
        }
    }


def _calibration(config: VehicleConfig, text: str) -> Calibration | None:
    if not text:
        return None
    try:
        return Calibration.from_file(parse_calibration(text, config.name, "<recorded>"))
    except CalibrationError as exc:
        raise ReplayError(f"the recorded calibration does not load here: {exc}") from exc


class Replayer:
    """Steps a core through recorded messages; `feed` them in order (one or more files)."""

    def __init__(
        self,
        core: ControlCore,
        tolerances: Iterable[Tolerance] = (),
        keep_divergences: int = 10,
        on_cycle: Callable[[int, float, ControlInputs, CoreOutput], None] | None = None,
    ) -> None:
        self.core = core
        self.tolerances = tuple(tolerances)
        self.keep_divergences = keep_divergences
        self.on_cycle = on_cycle
        self.result = ReplayResult()
        self._scans: dict[str, dict[int, MountedScan]] = {}
        self._started = False

    def feed(self, messages: Iterable[RecordedMessage]) -> ReplayResult:
        for message in messages:
            self.handle(message)
        return self.result

    def feed_file(self, file: Path | RecordingReader) -> RecordingReader:
        """Replay one file as it is read, taking only the topics replay uses; its reader
        (and report) back. The result's time span is still the file's whole span, every
        topic's first message to the last, as when every message is fed."""
        reader = file if isinstance(file, RecordingReader) else RecordingReader(file)
        report, result = reader.report, self.result
        for message in reader.messages(wanted=replayed_topic):
            if result.first_log_time_ns is None:
                result.first_log_time_ns = report.first_log_time_ns
            self.handle(message)
        if result.first_log_time_ns is None:
            result.first_log_time_ns = report.first_log_time_ns
        last = report.last_log_time_ns
        if last is not None and (result.last_log_time_ns is None or last > result.last_log_time_ns):
            result.last_log_time_ns = last
        return reader

    def handle(self, message: RecordedMessage) -> None:
        """One message, in recorded order; a topic replay does not use is passed over."""
        topic = message.topic
        result = self.result
        if result.first_log_time_ns is None:
            result.first_log_time_ns = message.log_time_ns
        result.last_log_time_ns = message.log_time_ns
        if topic == CYCLE_TOPIC:
            self._cycle(message)
        elif topic.startswith(SAMPLE_TOPIC_PREFIX + "scan."):
            self._scan(message)
        elif topic == RESET_TOPIC:
            self.core.reset()
            self._started = True
            result.resets += 1
        elif topic == REQUEST_TOPIC and self._started:
            self._request(message)

    def _scan(self, message: RecordedMessage) -> None:
        data = _json(message)
        side = message.topic.removeprefix(SAMPLE_TOPIC_PREFIX + "scan.")
        try:
            scan = decode(data["value"], MountedScan)
            seq = int(data["seq"])
        except (CodecError, KeyError, TypeError, ValueError) as exc:
            raise ReplayError(f"{message.topic} at {message.log_time_ns}: {exc}") from exc
        kept = self._scans.setdefault(side, {})
        kept[seq] = scan
        if len(kept) > SCANS_KEPT:
            del kept[min(kept)]

    def _request(self, message: RecordedMessage) -> None:
        data = _json(message)
        self.result.requests += 1
        name, kind = str(data.get("name", "")), data.get("kind")
        if kind == "bad_request":
            return  # refused by the socket's parser: it never reached the core
        if kind == "select_route":
            accepted, text = self.core.select_route(name)
        elif kind == "select_pallet":
            accepted, text = self.core.select_pallet(name)
        elif kind == "maneuver":
            action, _, step = name.partition(":")
            now_s = decode(data.get("now_s"), float)
            accepted, text = self.core.maneuver_request(action, step, now_s)
        else:
            accepted, text = self.core.request(name, decode(data.get("now_s"), float))
        recorded = [data.get("accepted"), data.get("message")]
        if [accepted, text] != recorded:
            self._diverged(
                message.log_time_ns,
                decode(data.get("now_s"), float | None) or math.nan,
                REQUEST_TOPIC,
                [("answer", recorded, [accepted, text])],
            )

    def _cycle(self, message: RecordedMessage) -> None:
        if not self._started:
            self.result.cycles_skipped += 1
            return
        data = _json(message)
        try:
            now_s = decode(data["now_s"], float)
            inputs = decode(data["inputs"], ControlInputs)
            scan_seqs = data.get("scan_seqs", {})
        except (CodecError, KeyError, TypeError) as exc:
            raise ReplayError(f"{CYCLE_TOPIC} at {message.log_time_ns}: {exc}") from exc
        scans = dict(inputs.scans)
        for side, seq in scan_seqs.items():
            if seq is None:
                scans.setdefault(side, None)
                continue
            scan = self._scans.get(side, {}).get(seq)
            if scan is None:
                raise ReplayError(
                    f"cycle at now_s {now_s} saw scan.{side} #{seq}, which is not in the "
                    "recording (the recorder dropped it: see /dbw/recorder)"
                )
            scans[side] = scan
        inputs = replace(inputs, scans=scans)
        output = self.core.step(inputs, now_s)
        self.result.cycles += 1
        if self.on_cycle is not None:
            self.on_cycle(message.log_time_ns, now_s, inputs, output)
        replayed = encode_fast(output, CoreOutput)
        if message.data.endswith(cycle_ending(replayed)):
            return  # the recorder's very bytes: the same output to the bit
        recorded = data.get("output")
        if json.dumps(replayed, sort_keys=True) == json.dumps(recorded, sort_keys=True):
            return  # written another way (another key order, say): the same values
        differences = [
            (path, r, p)
            for path, r, p in diff("output", recorded, replayed)
            if not self._tolerated(path, r, p)
        ]
        if differences:
            self._diverged(message.log_time_ns, now_s, CYCLE_TOPIC, differences)

    def _tolerated(self, path: str, recorded: Any, replayed: Any) -> bool:
        for tol in self.tolerances:
            if fnmatch.fnmatchcase(path, tol.pattern):
                if _is_number(recorded) and _is_number(replayed):
                    return bool(abs(float(recorded) - float(replayed)) <= tol.abs_tol)
                return False
        return False

    def _diverged(
        self, log_time_ns: int, now_s: float, topic: str, diffs: list[tuple[str, Any, Any]]
    ) -> None:
        self.result.divergent_cycles += 1
        for path, recorded, replayed in diffs:
            if len(self.result.divergences) >= self.keep_divergences:
                return
            self.result.divergences.append(
                Divergence(log_time_ns, now_s, topic, path, recorded, replayed)
            )


def replayed_topic(topic: str) -> bool:
    """The topics `Replayer.handle` acts on; the rest of a recording is for looking."""
    return topic in _REPLAYED_TOPICS or topic.startswith(_SCAN_TOPIC_PREFIX)


_REPLAYED_TOPICS = frozenset({CYCLE_TOPIC, RESET_TOPIC, REQUEST_TOPIC})
_SCAN_TOPIC_PREFIX = SAMPLE_TOPIC_PREFIX + "scan."


def _is_number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _json(message: RecordedMessage) -> dict[str, Any]:
    try:
        data = message.json()
    except ValueError as exc:
        raise ReplayError(f"{message.topic} at {message.log_time_ns}: not JSON: {exc}") from exc
    if not isinstance(data, dict):
        raise ReplayError(f"{message.topic} at {message.log_time_ns}: not a JSON object")
    return data


def diff(path: str, recorded: Any, replayed: Any) -> Iterator[tuple[str, Any, Any]]:
    """Every leaf where two JSON values differ, by dotted path (list items by index)."""
    if isinstance(recorded, dict) and isinstance(replayed, dict):
        for key in sorted(set(recorded) | set(replayed)):
            yield from diff(f"{path}.{key}", recorded.get(key), replayed.get(key))
    elif (
        isinstance(recorded, list) and isinstance(replayed, list) and len(recorded) == len(replayed)
    ):
        for index, (r, p) in enumerate(zip(recorded, replayed, strict=True)):
            yield from diff(f"{path}[{index}]", r, p)
    elif recorded != replayed or type(recorded) is not type(replayed):
        yield path, recorded, replayed
