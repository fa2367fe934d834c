"""Object files with a full covariance: what `dbw merge --out` writes and the `pallet`
source reads back."""

from __future__ import annotations

import json

import numpy as np
import pytest

from appliance.mapping.object_file import ObjectFileError, parse_object_map


def _file(**entry: object) -> bytes:
    base: dict[str, object] = {"name": "p1", "kind": "1200x800", "x_m": 1.0, "y_m": 2.0}
    base["yaw_deg"] = 30.0
    base.update(entry)
    return json.dumps({"frame": "vehicle", "objects": [base]}).encode()


def test_a_full_covariance_is_read_as_given() -> None:
    covariance = [[4e-4, 1e-5, 2e-6], [1e-5, 9e-4, -3e-6], [2e-6, -3e-6, 1e-4]]
    pallet_map = parse_object_map(_file(covariance_m_rad=covariance, seen_by="worker"))
    assert np.array_equal(pallet_map.pallets[0].covariance, np.array(covariance))
    assert pallet_map.frame == "vehicle"


@pytest.mark.parametrize(
    ("entry", "words"),
    [
        ({"covariance_m_rad": [[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}, "symmetric"),
        ({"covariance_m_rad": [[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]}, "semi-def"),
        ({"covariance_m_rad": [[1.0, 0.0], [0.0, 1.0]]}, "covariance_m_rad"),
        ({"covariance_m_rad": np.eye(3).tolist(), "sigma_xy_m": 0.01}, "not both"),
        ({"seen_by": "robot"}, "seen_by"),
    ],
)
def test_a_bad_covariance_or_provenance_is_refused_with_its_path(
    entry: dict[str, object], words: str
) -> None:
    with pytest.raises(ObjectFileError, match=words) as caught:
        parse_object_map(_file(**entry))
    assert "objects[0]" in str(caught.value)


def test_a_footprint_names_its_standard_pallet_to_the_millimetre() -> None:
    from appliance.mapping.pallets import PalletKind

    assert PalletKind.of_size(1.2, 0.8) is PalletKind.EUR
    assert PalletKind.of_size(1.1004, 1.0996) is PalletKind.JIS
    assert PalletKind.of_size(0.8, 1.2) is None  # the length is the longer side
    assert PalletKind.of_size(1.0, 1.2) is None
