"""The simulated site the simulated LMS111 scanners see, and how they see it.

``site`` holds the geometry (segments, circles, walking people) as frozen data,
``builders`` turns a few parameters into a launcher (Qian et al.), a pallet area
(Kinouchi et al.) or a yard, ``site_file`` loads a site from TOML, ``raycast`` finds
the nearest hit of every beam at once (a compiled loop, ``cast_kernels``),
``scanner_errors`` draws what one LMS111 gets wrong (noise, systematic error, beam
footprint, remission limit, mount error) and ``scanner_model`` renders one LMS111 scan
with the device's angle convention and errors.
Everything is pure: time and randomness are arguments, so the twins, the tests and
replays all get the same scans.
"""

from appliance.sim.builders import (
    LauncherSpec,
    PalletAreaSpec,
    PostSpec,
    SegmentSpec,
    WalkerSpec,
    YardSpec,
    clutter_site,
    launcher_docking_target,
    launcher_site,
    pallet_area_site,
    yard_site,
)
from appliance.sim.raycast import NO_HIT, RayHits, cast_rays, nearest_hits
from appliance.sim.scanner_errors import (
    LMS111_NOISE_SIGMA_M,
    TYPICAL_LMS111,
    BeamFootprint,
    RemissionLimit,
    ScannerErrors,
    draw_scanner_errors,
    ideal_scanner,
    statistical_only,
)
from appliance.sim.scanner_model import (
    LMS111_MAX_RANGE_M,
    LMS111_START_ANGLE_RAD,
    LMS111_STEP_RAD,
    LMS111_STOP_ANGLE_RAD,
    beam_angles_rad,
    render_scan,
    scanner_pose,
)
from appliance.sim.site import Circle, Segment, ShapeArrays, Site, Walker
from appliance.sim.site_file import SiteError, SiteFile, builtin_site_names, load_site, parse_site
from drivers.geometry import Pose2D

__all__ = [
    "LMS111_MAX_RANGE_M",
    "LMS111_NOISE_SIGMA_M",
    "LMS111_START_ANGLE_RAD",
    "LMS111_STEP_RAD",
    "LMS111_STOP_ANGLE_RAD",
    "NO_HIT",
    "TYPICAL_LMS111",
    "BeamFootprint",
    "Circle",
    "LauncherSpec",
    "PalletAreaSpec",
    "Pose2D",
    "PostSpec",
    "RayHits",
    "RemissionLimit",
    "ScannerErrors",
    "Segment",
    "SegmentSpec",
    "ShapeArrays",
    "Site",
    "SiteError",
    "SiteFile",
    "Walker",
    "WalkerSpec",
    "YardSpec",
    "beam_angles_rad",
    "builtin_site_names",
    "cast_rays",
    "clutter_site",
    "draw_scanner_errors",
    "ideal_scanner",
    "launcher_docking_target",
    "launcher_site",
    "load_site",
    "nearest_hits",
    "pallet_area_site",
    "parse_site",
    "render_scan",
    "scanner_pose",
    "statistical_only",
    "yard_site",
]
