"""`dbw calibrate STEP` and `dbw calibrate fit FILE`: the maneuvers, run against the daemon.

Each step checks its preconditions (and says every one that fails), prompts the
technician, asks for the area-clear confirmation, taps the daemon's cycles while the
technician does the maneuver, shows coverage and an ETA, and ends on completion, Ctrl-C,
a timeout, or anything that makes the data worthless or the vehicle unsafe
(``appliance.maneuvers.runner``). The raw samples go to a file as they arrive (``--samples``;
``--resume FILE`` continues an interrupted run), and the daemon's recorder keeps the same
cycles. Then the fit: its method, residuals and verdict are printed, a PNG is drawn, and
an accepted result is merged into the calibration file atomically
(``appliance.maneuvers.merge``). `dbw calibrate fit FILE` fits a samples file again.

Exit status: 0 accepted (and merged unless --no-merge), 1 refused, aborted or not
accepted (the calibration file untouched), 2 bad input or no daemon.
"""

from __future__ import annotations

import asyncio
import json
import sys
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, NoReturn

import click

from appliance import __version__
from appliance.cli.common import CONFIG_OPTION, EXIT_CONFIG_ERROR, draw_png, load_or_exit
from appliance.config import VehicleConfig
from appliance.config.calibration import CalibrationFile
from appliance.config.calibration_file import (
    BUILTIN_SIMULATED,
    CalibrationError,
    read_vehicle_calibration,
)
from appliance.control_client import ControlClient
from appliance.control_protocol import ControlSocketError
from appliance.maneuvers.merge import MergeError, draft_values, merge_result
from appliance.maneuvers.registry import STEP_CLASSES
from appliance.maneuvers.report import FitReport
from appliance.maneuvers.runner import ManeuverRunner, RefusedError
from appliance.maneuvers.samples_file import (
    SamplesFileError,
    SamplesWriter,
    header,
    read_samples_file,
)
from appliance.maneuvers.steps import StepContext

EXIT_NOT_ACCEPTED = 1


def _fail(message: str, code: int = EXIT_CONFIG_ERROR) -> NoReturn:
    click.echo(f"dbw calibrate: {message}", err=True)
    sys.exit(code)


def _existing(config: VehicleConfig, path: str) -> CalibrationFile | None:
    """The calibration the step builds on, or None (a first installation)."""
    if path != BUILTIN_SIMULATED and not Path(path).exists():
        return None
    try:
        return read_vehicle_calibration(config, path)
    except CalibrationError as exc:
        click.echo(f"note: {exc.render()}\n(the step runs without it)", err=True)
        return None


def _context(config: VehicleConfig, target: str, extra: dict[str, Any]) -> StepContext:
    """What a step builds on: the calibration file, else (a first installation) what
    the draft already holds (the pot centre the pot map is measured from)."""
    existing = _existing(config, target)
    options = dict(extra)
    if existing is None and target != BUILTIN_SIMULATED:
        try:
            steering = draft_values(config, target).get("steering", {})
        except MergeError as exc:
            _fail(str(exc))
        if "pot_centre_counts" in steering:
            options.setdefault("x_pot_centre_counts", steering["pot_centre_counts"])
    return StepContext(config, existing, options)


def _step_options(command: Any) -> Any:
    options = [
        CONFIG_OPTION,
        click.option("--socket", "socket_path", metavar="PATH", help="The control socket."),
        click.option(
            "--calibration",
            "calibration_path",
            metavar="FILE",
            help="The calibration file to merge into (default: paths.calibration_file).",
        ),
        click.option("--samples", "samples_path", metavar="FILE", help="Where the raw samples go."),
        click.option(
            "--resume", "resume_path", metavar="FILE", help="Continue an interrupted run."
        ),
        click.option("--yes", is_flag=True, help="Confirm the area is clear without asking."),
        click.option(
            "--timeout",
            "timeout_s",
            type=click.FloatRange(min=1.0),
            default=None,
            help="Give up after this many seconds (default: the step's own: 15 min by hand, "
            "1 h for the pedal sweep, 4 h for the look-ahead runs); the vehicle is left "
            "safe and --resume goes on.",
        ),
        click.option("--png", "png_path", metavar="FILE", help="The figure (default: beside)."),
        click.option("--no-merge", is_flag=True, help="Fit and report; leave the file alone."),
    ]
    for option in reversed(options):
        command = option(command)
    return command


def _run_step(
    step_name: str,
    config_name: str | None,
    socket_path: str | None,
    calibration_path: str | None,
    samples_path: str | None,
    resume_path: str | None,
    yes: bool,
    timeout_s: float | None,
    png_path: str | None,
    no_merge: bool,
    extra: dict[str, Any],
) -> None:
    from appliance.cli.control import _socket_path

    config = load_or_exit(config_name)
    target = calibration_path or config.paths.calibration_file
    step = STEP_CLASSES[step_name](_context(config, target, extra))
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    if resume_path is not None:
        try:
            previous = read_samples_file(resume_path, config.name)
        except SamplesFileError as exc:
            _fail(str(exc))
        if previous.step != step_name:
            _fail(f"{resume_path} holds a {previous.step} run, not {step_name}")
        for sample in previous.samples:
            step.update(sample)
        path = Path(resume_path)
        writer = SamplesWriter(path, None)
        writer.mark("resumed", samples=len(previous.samples))
        click.echo(f"resuming {path}: {len(previous.samples)} samples taken before")
    else:
        path = Path(samples_path or f"{step_name}-{stamp}.jsonl")
        try:
            writer = SamplesWriter(path, header(step_name, config.name, __version__, stamp))
        except OSError as exc:
            _fail(f"{path}: cannot write the samples: {exc}")

    def confirm(question: str) -> bool:
        return yes or click.confirm(question, default=False)

    async def run() -> Any:
        async with ControlClient(_socket_path(socket_path, config_name), timeout_s=5.0) as client:
            runner = ManeuverRunner(
                step,
                client,
                writer,
                sys.stdout,
                timeout_s=step.default_timeout_s if timeout_s is None else timeout_s,
                confirm=confirm,
            )
            return await runner.run()

    try:
        outcome = asyncio.run(run())
    except RefusedError as exc:
        _fail(f"{step_name} refused: {exc}", EXIT_NOT_ACCEPTED)
    except ControlSocketError as exc:
        _fail(str(exc))
    except KeyboardInterrupt:
        _fail(f"interrupted; the calibration is untouched; resume with --resume {path}", 1)
    finally:
        writer.close()
    click.echo(f"{step_name}: {outcome.reason} ({outcome.samples} samples, {outcome.missed} lost)")
    if not outcome.complete:
        _fail(
            f"the calibration is untouched; resume with: dbw calibrate {step_name} --resume {path}",
            EXIT_NOT_ACCEPTED,
        )
    _fit_and_merge(step_name, config, path, target, png_path, no_merge, extra)


def _fit_and_merge(
    step_name: str,
    config: VehicleConfig,
    samples: Path,
    target: str,
    png_path: str | None,
    no_merge: bool,
    extra: dict[str, Any],
    as_json: bool = False,
) -> None:
    step_name, taken = _samples(config, samples, step_name or None)
    step = STEP_CLASSES[step_name](_context(config, target, extra))
    # Absolute: the record is read from elsewhere (k-ratio refits the palm tree from it).
    report: FitReport = step.fit(taken, raw_data=str(samples.resolve()))
    if as_json:
        click.echo(
            json.dumps(
                {
                    "step": report.step,
                    "accepted": report.accepted,
                    "reasons": list(report.reasons),
                    **report.figures,
                }
            )
        )
    else:
        for line in report.lines:
            click.echo(line)
    if report.draw is not None:
        png = png_path or str(samples.with_suffix(".png"))
        problem = draw_png(png, report.draw)
        click.echo(f"figure: {problem or png}", err=as_json)
    if not report.accepted or report.result is None:
        _fail("not accepted: " + "; ".join(report.reasons), EXIT_NOT_ACCEPTED)
    if no_merge:
        click.echo("accepted; the calibration file is left as it is", err=as_json)
        return
    try:
        said = merge_result(config, target, report.result)
    except (MergeError, OSError, ValueError) as exc:
        _fail(f"accepted but not merged: {exc}")
    click.echo(said, err=as_json)
    if said.endswith(" merged"):
        # The daemon reads its calibration once, at start: the next step (the palm tree
        # after the pot map) must not run on the old one.
        click.echo(
            "the running daemon keeps the calibration it started with: restart it "
            "(sudo systemctl restart dbw) before the next step or drive",
            err=as_json,
        )


def _samples(
    config: VehicleConfig, path: Path, step_name: str | None
) -> tuple[str, list[dict[str, Any]]]:
    """A step's samples from a samples file, or from a flight recording (``.mcap``: its
    session replayed, the tap run again over the same cycles; the last run of the step)."""
    if path.suffix == ".mcap":
        # Replay brings the whole control core with it: imported only for a recording.
        from appliance.maneuvers.from_recording import RecordingSamplesError, maneuver_samples

        try:
            vehicle, run = maneuver_samples(path, step_name)
        except (RecordingSamplesError, OSError) as exc:
            _fail(str(exc))
        if vehicle != config.name:
            _fail(f"{path}: recorded on vehicle {vehicle!r}, not {config.name!r}")
        if run.step not in STEP_CLASSES:
            _fail(f"{path}: no fit for the {run.step} maneuver in this dbw yet")
        click.echo(f"{path}: the {run.step} run replayed, {len(run.samples)} samples", err=True)
        return run.step, run.samples
    try:
        data = read_samples_file(path, config.name)
    except SamplesFileError as exc:
        _fail(str(exc))
    if data.torn_last_line:
        click.echo(f"note: {path}: the last line was cut short and is left out", err=True)
    if step_name is not None and data.step != step_name:
        _fail(f"{path} holds a {data.step} run, not {step_name}")
    return data.step, data.samples


def add_maneuver_commands(group: click.Group) -> None:
    """Register one command per step, and `fit`, on the `dbw calibrate` group."""
    for name, step_class in STEP_CLASSES.items():
        group.add_command(_step_command(name, step_class.summary, step_class.extra_options))
    group.add_command(fit)


def _step_command(name: str, summary: str, extra_options: tuple[Any, ...]) -> click.Command:
    def command(**kwargs: Any) -> None:
        extra = {key: kwargs.pop(key) for key in list(kwargs) if key.startswith("x_")}
        _run_step(name, extra=extra, **kwargs)

    command.__doc__ = summary
    decorated = _step_options(command)
    for option in extra_options:
        decorated = option(decorated)
    return click.command(name)(decorated)


@click.command("fit")
@click.argument("file")
@CONFIG_OPTION
@click.option("--calibration", "calibration_path", metavar="FILE", help="The file to merge into.")
@click.option("--png", "png_path", metavar="FILE", help="The figure (default: beside FILE).")
@click.option("--merge", is_flag=True, help="Merge an accepted result into the calibration.")
@click.option("--json", "as_json", is_flag=True, help="Print the figures as one JSON object.")
@click.option(
    "--step",
    "step_name",
    type=click.Choice(sorted(STEP_CLASSES)),
    help="Which maneuver (a recording may hold several; default: its last).",
)
@click.option(
    "--steering-ratio",
    "x_steering_ratio",
    type=click.FloatRange(min=1.0, max=60.0),
    help="pot-map: where no calibration gives it.",
)
@click.option(
    "--counts-per-tyre-deg", "x_counts_per_tyre_deg", type=float, help="pot-center: likewise."
)
@click.option(
    "--pot-centre-counts",
    "x_pot_centre_counts",
    type=click.FloatRange(min=0.0, max=4095.0),
    help="pot-map: the centre to fit about (default: the calibration's, or the draft's).",
)
def fit(
    file: str,
    config_name: str | None,
    calibration_path: str | None,
    png_path: str | None,
    merge: bool,
    as_json: bool,
    step_name: str | None,
    **extra: Any,
) -> None:
    """Fit a maneuver's samples FILE again (offline; the daemon is not needed). FILE is a
    samples file, or a flight recording (.mcap) whose maneuver is replayed to get them."""
    config = load_or_exit(config_name)
    target = calibration_path or config.paths.calibration_file
    options = {key: value for key, value in extra.items() if value is not None}
    _fit_and_merge(
        step_name or "", config, Path(file), target, png_path, not merge, options, as_json
    )
