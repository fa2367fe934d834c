"""A pallet map from a file's bytes, whichever form a terminal handed over.

A worker's map comes as a PLY point cloud (`cloud_file`; its pallets found through
proximity points, `cloud_pallets`) or as a JSON object list (`object_file`), told apart
by the first bytes. `dbw merge` and the `pallet` autopilot source read it the same way,
so a file that merges at the desk merges on the vehicle. Every defect is a
`MapFileError` naming it; nothing is half read.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy.typing as npt

from appliance.mapping.cloud_file import CloudFileError, parse_ply
from appliance.mapping.cloud_pallets import CloudPalletParams, CloudPallets, detect_pallets
from appliance.mapping.object_file import ObjectFileError, parse_object_map
from appliance.mapping.pallet_fit import ALL_KINDS
from appliance.mapping.pallets import Pallet, PalletKind, PalletMap

MAX_MAP_BYTES = 2 * 1024**3  # a 2 GiB cloud is ~100 million float32 points: enough
# A cloud without viewpoints is taken as seen from its origin at a hand-held height.
DEFAULT_ORIGIN_HEIGHT_M = 1.2


class MapFileError(ValueError):
    """A map file that cannot be used, and why (the file named)."""


@dataclass(frozen=True)
class MapRead:
    pallet_map: PalletMap
    cloud: CloudPallets | None  # the detection, where the file was a cloud
    notes: tuple[str, ...] = ()  # what was left out, in words
    # A cloud's faces read once per kind (`cloud_alternatives`), for the merge's fit.
    alternatives: tuple[Pallet, ...] = ()


def cloud_alternatives(
    xyz_m: npt.ArrayLike, origins: npt.ArrayLike, kinds: tuple[PalletKind, ...] = ALL_KINDS
) -> tuple[Pallet, ...]:
    """The cloud's pallets found with one kind allowed at a time: a face the map could
    not tell (1.1 m: a 1100x1100's side or a 1200x800's long one) is then read as each,
    and the merge may pair the right reading with the vehicle's pallet
    (`merge_maps(..., alternatives=)`). Never a map of their own: most are misreadings."""
    found: list[Pallet] = []
    for kind in kinds:
        params = CloudPalletParams(kinds=(kind,))
        found.extend(detect_pallets(xyz_m, origins, params, frame="worker").pallet_map.pallets)
    return tuple(found)


def is_ply(data: bytes) -> bool:
    return data[:4] == b"ply\n" or data[:5] == b"ply\r\n"


def pallet_map_from_bytes(
    data: bytes,
    source: str,
    frame: str,
    origin_height_m: float = DEFAULT_ORIGIN_HEIGHT_M,
    with_alternatives: bool = False,
) -> MapRead:
    """The pallets of ``data`` in ``frame``; a cloud's from its ``comment dbw origin``
    viewpoints, else from its origin ``origin_height_m`` above the floor (and, asked
    for, its `cloud_alternatives`: three detections' time)."""
    if is_ply(data):
        try:
            cloud = parse_ply(data, drop_non_finite=True)
        except CloudFileError as exc:
            raise MapFileError(f"{source}: {exc}") from exc
        notes = []
        if cloud.dropped_non_finite:
            notes.append(f"{source}: {cloud.dropped_non_finite} points not finite, left out")
        origins = list(cloud.origins_m) or [(0.0, 0.0, origin_height_m)]
        found = detect_pallets(cloud.xyz_m, origins, frame=frame)
        alternatives = cloud_alternatives(cloud.xyz_m, origins) if with_alternatives else ()
        return MapRead(replace(found.pallet_map, source=source), found, tuple(notes), alternatives)
    try:
        pallet_map = parse_object_map(data, source=source)
    except ObjectFileError as exc:
        raise MapFileError(f"{source}: {exc}") from exc
    return MapRead(replace(pallet_map, frame=frame), None)


def read_pallet_map(
    path: Path | str,
    frame: str,
    origin_height_m: float = DEFAULT_ORIGIN_HEIGHT_M,
    with_alternatives: bool = False,
) -> MapRead:
    """`pallet_map_from_bytes` of the file at ``path`` (refused past `MAX_MAP_BYTES`
    before reading it)."""
    file = Path(path)
    try:
        if file.stat().st_size > MAX_MAP_BYTES:
            raise MapFileError(f"{path}: larger than {MAX_MAP_BYTES // 1024**3} GiB")
        data = file.read_bytes()
    except OSError as exc:
        raise MapFileError(f"{path}: cannot read it: {exc.strerror or exc}") from exc
    return pallet_map_from_bytes(data, str(path), frame, origin_height_m, with_alternatives)
