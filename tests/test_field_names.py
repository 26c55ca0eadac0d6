"""``sdp distance --field-names``: the names CloudCompare's M3C2 and PDAL's filters.m3c2 give the
distances' fields (issue 35)."""

import subprocess
import sys

import numpy as np
import pytest

import sdp
from sdp.cli import distance_files
from sdp.distance._distances import DISTANCE_FIELDS
from sdp.distance._names import FIELD_NAMES


@pytest.fixture(scope="module")
def epochs(tmp_path_factory):
    d = tmp_path_factory.mktemp("names")
    rng = np.random.default_rng(3)
    a = np.c_[rng.random((4000, 2)), np.zeros(4000)]
    np.save(d / "a.npy", a)
    np.save(d / "b.npy", a + [0, 0, 0.02])
    return d


def test_every_convention_names_every_field_within_a_las_name():
    for names in FIELD_NAMES.values():
        assert set(names) == set(DISTANCE_FIELDS)
        assert len(set(names.values())) == len(names) and all(len(n) <= 32 for n in names.values())


@pytest.mark.parametrize("convention", ["cloudcompare", "pdal"])
def test_las_output_reads_back_with_the_tools_names(epochs, tmp_path, convention):
    import laspy

    ours = distance_files(epochs / "a.npy", epochs / "b.npy", output=tmp_path / "sdp.laz")
    theirs = distance_files(epochs / "a.npy", epochs / "b.npy", output=tmp_path / "out.laz",
                            outputs=sdp.Outputs(field_names=convention))
    las = laspy.read(tmp_path / "out.laz")
    names = FIELD_NAMES[convention]
    assert set(las.point_format.extra_dimension_names) == set(names.values())
    back = laspy.read(tmp_path / "sdp.laz")
    for field, name in names.items():
        assert np.array_equal(np.asarray(las[name]), np.asarray(back[field]), equal_nan=True), name
    assert np.allclose(np.asarray(las[names["distance"]]), 0.02, atol=1e-3)
    assert ours.summary["comparable"] == theirs.summary["comparable"]


def test_ply_names_hold_no_space_and_the_flag_is_checked(epochs, tmp_path):
    p = subprocess.run([sys.executable, "-m", "sdp.cli", "distance", epochs / "a.npy", epochs / "b.npy", "-o",
                        tmp_path / "d.ply", "--field-names", "cloudcompare", "-q"], capture_output=True, text=True)
    assert p.returncode == 0, p.stderr
    names = set(sdp.read_points(tmp_path / "d.ply").fields)
    assert {"M3C2_distance", "distance_uncertainty", "significant_change"} <= names
    with pytest.raises(sdp.InvalidOptionError, match="field_names must be one of sdp, cloudcompare, pdal"):
        sdp.Outputs(field_names="qgis")
