"""The simulated scanners' calibration, copied from the simulator's truth.

``builtin:simulated`` is the simulated vehicle's true calibration (the pot mapping is fitted
from the simulated pot, ``appliance.config.simulated_calibration``). For a simulated
flat-bed or forklift it also holds each scanner's truth: the range offset and mount error the
simulator drew for it (``draw_scanner_errors``), as if ``dbw calibrate scanners`` had
measured them perfectly. Here, in the simulation's layer, because only it knows them; the
daemon and ``dbw calibration write-simulated`` add them. To calibrate the simulated
scanners the way a technician would, run ``dbw calibrate scanners`` on recordings of them
instead: the figures then include the fit's own error.
"""

from __future__ import annotations

import math
from datetime import UTC, datetime

from appliance.config.calibration import CalibrationFile, ScannerCalibrationEntry
from appliance.config.calibration_file import with_scanners
from appliance.config.models import VehicleConfig, VehicleKind
from appliance.sim.scanner_errors import draw_scanner_errors
from drivers.lms111.mounted import mount_pose

TRUTH_RANGE_SIGMA_M = 0.001
TRUTH_YAW_SIGMA_DEG = 0.01


def simulated_scanner_entries(config: VehicleConfig) -> dict[str, ScannerCalibrationEntry]:
    """Each simulated front scanner's true errors as calibration entries."""
    sim = config.simulation
    realistic = sim.scanner_model == "realistic"
    mounts = {
        "left": config.geometry.scanner_left_mount,
        "right": config.geometry.scanner_right_mount,
    }
    entries = {}
    for index, (name, mount) in enumerate(mounts.items()):
        errors = draw_scanner_errors(sim.scanner_seed, index, realistic)
        configured = mount_pose(mount)
        true = errors.true_mount(configured)
        entries[name] = ScannerCalibrationEntry(
            range_offset_m=errors.range_offset_m,
            range_offset_sigma_m=TRUTH_RANGE_SIGMA_M,
            mount_yaw_offset_deg=math.degrees(true.yaw_rad - configured.yaw_rad),
            mount_yaw_offset_sigma_deg=TRUTH_YAW_SIGMA_DEG,
            lateral_offset_m=true.y_m - configured.y_m,
            lateral_offset_sigma_m=TRUTH_RANGE_SIGMA_M,
            residual_rms_m=0.0,
            method=f"simulator truth (scanner_seed {sim.scanner_seed}, {sim.scanner_model})",
            measured_utc=datetime.now(UTC),
        )
    return entries


def with_simulated_scanners(model: CalibrationFile, config: VehicleConfig) -> CalibrationFile:
    """``model`` with the simulated scanners' truth, for a simulated vehicle that
    localizes on them (a flat-bed, a forklift); else as is."""
    localizes = config.kind in (VehicleKind.FLATBED, VehicleKind.FORKLIFT)
    if not localizes or not config.simulation.enabled:
        return model
    return with_scanners(model, simulated_scanner_entries(config))
