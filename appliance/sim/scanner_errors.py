"""What a SICK LMS111 gets wrong, drawn once per scanner from a seed.

The figures, each with its source (the LMS111 data sheet and the LMS1xx operating
instructions, SICK 8012471, section 3.6, unless marked as a choice of ours):

- Statistical error 12 mm, 1 sigma, typical (data sheet): white Gaussian noise, one
  draw per beam per scan.
- Systematic error +-30 mm, typical (data sheet). The data sheet gives a bound and no
  distribution, so a unit's error is drawn uniformly inside it and kept: a range offset
  of up to +-20 mm and a scale error of up to +-0.05 % of the range (+-10 mm at 20 m),
  together never more than the +-30 mm anywhere in the 20 m range. The scale term is our
  choice: SICK describes the LMS1xx's error as changing with distance (about 23 mm at
  1 m, more nearer and farther: SICK USA blog, "How to minimize the systematic and
  statistical error of SICK LMS devices"), and a linear term is the first-order form.
- Beam footprint: diameter = 8 mm + 15 mrad x range (operating instructions, 3.6.2).
  Its profile across the scan plane is taken as Gaussian with the stated diameter at
  1/e^2 (the usual laser beam diameter convention; SICK states none).
- Echo evaluation (ours, for a pulsed time-of-flight receiver): returns less than the
  pulse length apart in range, taken as 0.6 m (a ~4 ns laser pulse: c x 4 ns / 2),
  overlap and arrive as one pulse, measured at their energy-weighted range; farther-apart
  echoes stay separate and the device reports the first one strong enough, as a
  first-echo device does; a beam with too little energy returns no echo (range 0).
  A return is what one sub-ray of the footprint hits (``BeamFootprint.sub_rays``, 7).
- Energy: proportional to remission / range^2 (a diffuse target filling the beam). The
  data sheet's 18 m at 10 % remission fixes the detection threshold: the device needs a
  remission of at least 0.10 x (range / 18 m)^2, i.e. 3 % at 10 m, 12 % at the 20 m
  maximum. Retro-reflectors (remission > 1) are seen to the maximum range.
- Mount (ours): a bracket bolted on without a survey sits a few millimetres and a few
  tenths of a degree off its drawing: x and y each uniform in +-5 mm, yaw uniform in
  +-0.3 degree, per vehicle and scanner. The scanner measures from its true mount; the
  daemon only knows the configured one.

``ideal_scanner()`` has none of these: exact geometry up to the maximum range.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from appliance.sim.cast_kernels import first_strong_echo_into
from drivers.geometry import Pose2D

LMS111_NOISE_SIGMA_M = 0.012  # the data sheet's statistical error, taken as 1 sigma
LMS111_SYSTEMATIC_ERROR_M = 0.030  # the data sheet's systematic error (a bound, typical)
MAX_RANGE_OFFSET_M = 0.020  # ours: the part of the +-30 mm that is a constant offset
# Ours: the rest, proportional to range, reaching it at the 20 m maximum range (0.05 %).
MAX_RANGE_SCALE = (LMS111_SYSTEMATIC_ERROR_M - MAX_RANGE_OFFSET_M) / 20.0
MAX_MOUNT_OFFSET_M = 0.005  # ours: per axis
MAX_MOUNT_YAW_RAD = math.radians(0.3)  # ours
NO_MOUNT_ERROR = Pose2D(0.0, 0.0, 0.0)

_ERROR_STREAM = 0x5C4E  # keeps these draws apart from other streams of the same seed
_NOISE_STREAM = 0x4E01


@dataclass(frozen=True)
class BeamFootprint:
    """The beam's width and how the echoes within it combine.

    Sub-rays sample the footprint at ``sub_rays`` points (an odd count, so the middle
    one is the central ray) across its 1/e^2 diameter, weighted by a Gaussian profile.
    """

    exit_diameter_m: float = 0.008
    divergence_rad: float = 0.015  # full angle
    pulse_merge_m: float = 0.6  # echoes closer than this in range merge into one
    sub_rays: int = 7

    def __post_init__(self) -> None:
        if self.sub_rays < 3 or self.sub_rays % 2 == 0:
            raise ValueError(f"sub_rays must be odd and >= 3, got {self.sub_rays}")
        if not (self.exit_diameter_m >= 0.0 and self.divergence_rad >= 0.0):
            raise ValueError("exit_diameter_m and divergence_rad must be >= 0")
        if not self.pulse_merge_m >= 0.0:
            raise ValueError(f"pulse_merge_m must be >= 0, got {self.pulse_merge_m}")

    def diameter_m(self, range_m: float) -> float:
        """The footprint's diameter where the beam meets a surface ``range_m`` away."""
        return self.exit_diameter_m + self.divergence_rad * range_m

    def half_angle_rad(self, range_m: NDArray[np.float64]) -> NDArray[np.float64]:
        """Half the angle the footprint subtends from the scanner at ``range_m``.

        Exact at that range; sub-rays from the scanner's origin fan out by this angle,
        so a second surface much nearer or farther than ``range_m`` sees the divergence
        right but the 8 mm exit diameter scaled (it only matters within a metre or so).
        """
        near_m = np.maximum(range_m, 0.05)
        result: NDArray[np.float64] = (
            0.5 * self.divergence_rad + 0.5 * self.exit_diameter_m / near_m
        )
        return result

    @functools.cached_property
    def profile(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Sub-ray offsets (fractions of the half-width, -1..1) and weights (sum 1).

        Midpoints of equal bins, so the middle offset is exactly 0 (the central ray).
        """
        count = self.sub_rays
        offsets = (2.0 * np.arange(count) + 1.0) / count - 1.0
        weights = np.exp(-2.0 * offsets * offsets)  # 1/e^2 at the footprint's edge
        weights /= weights.sum()
        offsets.flags.writeable = False
        weights.flags.writeable = False
        return offsets, weights

    @functools.cached_property
    def side_offsets(self) -> NDArray[np.float64]:
        """``profile``'s offsets without the middle one: the sub-rays besides the central ray."""
        offsets, _ = self.profile
        side = np.delete(offsets, offsets.size // 2)
        side.flags.writeable = False
        return side


@dataclass(frozen=True)
class RemissionLimit:
    """The weakest echo the device detects: ``remission`` at ``range_m``, energy ~ rho / r^2."""

    remission: float = 0.10
    range_m: float = 18.0

    def __post_init__(self) -> None:
        if not (self.remission > 0.0 and self.range_m > 0.0):
            raise ValueError("remission and range_m must be > 0")

    @property
    def min_energy(self) -> float:
        """The detection threshold in the units of ``echo_energy`` (remission / m^2)."""
        return self.remission / (self.range_m * self.range_m)

    def min_remission(self, range_m: float) -> float:
        """The least remission a target filling the beam needs to be seen at ``range_m``."""
        return self.remission * (range_m / self.range_m) ** 2

    def max_range_m(self, remission: float) -> float:
        """How far a target of ``remission`` filling the beam is seen (before the 20 m cap)."""
        return self.range_m * math.sqrt(max(remission, 0.0) / self.remission)


@dataclass(frozen=True)
class ScannerErrors:
    """One scanner's errors: its drawn systematic errors and the device's random ones.

    A measured range is ``true * (1 + range_scale) + range_offset_m + N(0, noise_sigma_m)``
    of the echo the footprint and the receiver make of the scene (``footprint``; None: a
    thin ray), and only if strong enough (``remission_limit``; None: every hit within
    the maximum range). The scanner sits at ``configured_mount o mount_error``.
    The defaults are a typical LMS111 with no systematic error; `draw_scanner_errors`
    adds a unit's.
    """

    range_offset_m: float = 0.0
    range_scale: float = 0.0  # fractional: 0.0005 reads 10 mm long at 20 m
    noise_sigma_m: float = LMS111_NOISE_SIGMA_M
    mount_error: Pose2D = NO_MOUNT_ERROR  # the true mount in the configured mount's frame
    footprint: BeamFootprint | None = field(default_factory=BeamFootprint)
    remission_limit: RemissionLimit | None = field(default_factory=RemissionLimit)
    ideal: bool = False

    def __post_init__(self) -> None:
        if not self.noise_sigma_m >= 0.0:
            raise ValueError(f"noise_sigma_m must be >= 0, got {self.noise_sigma_m}")
        neutral = (
            self.range_offset_m == 0.0
            and self.range_scale == 0.0
            and self.noise_sigma_m == 0.0
            and Pose2D(*self.mount_error) == NO_MOUNT_ERROR
            and self.footprint is None
            and self.remission_limit is None
        )
        if self.ideal and not neutral:
            raise ValueError("an ideal scanner has no errors: use ideal_scanner()")

    def true_mount(self, configured: Pose2D | tuple[float, float, float]) -> Pose2D:
        """Where the scanner really sits on the vehicle, given where it is said to."""
        return Pose2D(*configured).compose(Pose2D(*self.mount_error))


TYPICAL_LMS111 = ScannerErrors()  # the data sheet's random errors, no systematic ones


def ideal_scanner() -> ScannerErrors:
    """A scanner that measures the geometry exactly: the model switched off."""
    return ScannerErrors(noise_sigma_m=0.0, footprint=None, remission_limit=None, ideal=True)


def statistical_only(
    range_offset_m: float = 0.0, noise_sigma_m: float = LMS111_NOISE_SIGMA_M
) -> ScannerErrors:
    """A thin ray with a fixed offset and white noise: the simulator's model before this one."""
    return ScannerErrors(
        range_offset_m=range_offset_m,
        noise_sigma_m=noise_sigma_m,
        footprint=None,
        remission_limit=None,
    )


def draw_scanner_errors(seed: int, scanner_index: int, realistic: bool) -> ScannerErrors:
    """The errors of scanner ``scanner_index`` of the vehicle ``seed`` stands for.

    The same (seed, index) always gives the same errors, and another index another
    unit's; ``realistic=False`` gives the ideal scanner.
    """
    if not realistic:
        return ideal_scanner()
    rng = np.random.default_rng(np.random.SeedSequence([_ERROR_STREAM, seed, scanner_index]))
    offset_m, scale, dx_m, dy_m, dyaw_rad = rng.uniform(-1.0, 1.0, size=5) * (
        MAX_RANGE_OFFSET_M,
        MAX_RANGE_SCALE,
        MAX_MOUNT_OFFSET_M,
        MAX_MOUNT_OFFSET_M,
        MAX_MOUNT_YAW_RAD,
    )
    return ScannerErrors(
        range_offset_m=float(offset_m),
        range_scale=float(scale),
        mount_error=Pose2D(float(dx_m), float(dy_m), float(dyaw_rad)),
    )


def noise_seed(seed: int, scanner_index: int) -> int:
    """A seed for a scanner's per-scan noise, apart from the stream of its drawn errors."""
    state = np.random.SeedSequence([_NOISE_STREAM, seed, scanner_index]).generate_state(1)
    return int(state[0])


def echo_energy(
    ranges_m: NDArray[np.float64], remission: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Received energy of a target filling the beam, in remission / m^2 (0 for no hit)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        energy = np.where(ranges_m > 0.0, remission / (ranges_m * ranges_m), 0.0)
    result: NDArray[np.float64] = energy
    return result


def first_strong_echo(
    ranges_m: NDArray[np.float64],
    energy: NDArray[np.float64],
    pulse_merge_m: float,
    min_energy: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """What a pulsed receiver makes of several returns per beam: (range, energy) per row.

    ``ranges_m`` and ``energy`` are (beams, returns), 0 range = no return. Returns are
    taken nearest first, and one within ``pulse_merge_m`` of the previous one overlaps
    its pulse: they arrive as one echo, whose energy is their sum and whose range is
    their energy-weighted mean. A larger gap starts the next echo. The first echo with
    at least ``min_energy`` (more than 0 if ``min_energy`` is 0) is the measurement; a
    beam without one gets range 0 and energy 0 (`cast_kernels.first_strong_echo_into`).
    """
    beams = ranges_m.shape[0]
    found_m, found_energy = np.empty(beams), np.empty(beams)
    first_strong_echo_into(ranges_m, energy, pulse_merge_m, min_energy, found_m, found_energy)
    return found_m, found_energy
