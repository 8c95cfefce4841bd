"""BOP19 submission CSV: naming, round trip (mm on disk, metres in memory), validation."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dope_hope.errors import InputFileError
from dope_hope.io.bop_csv import (
    BopEstimate,
    bop_result_filename,
    parse_bop_result_filename,
    read_bop_csv,
    write_bop_csv,
)


def estimates() -> list[BopEstimate]:
    rng = np.random.default_rng(0)
    out = []
    for k in range(5):
        out.append(BopEstimate(scene_id=1 + k // 3, im_id=k, obj_id=11 + k, score=0.9 - 0.1 * k,
                               R=Rotation.random(random_state=k).as_matrix(),
                               t=rng.normal(scale=0.2, size=3) + [0, 0, 0.8], time=0.25 + k // 3))
    return out


def test_round_trip_is_exact_and_translation_is_millimetres_on_disk(tmp_path):
    path = tmp_path / "dopehope-dr50_hope-test.csv"
    ests = estimates()
    assert write_bop_csv(path, ests) == path
    lines = path.read_text().splitlines()
    assert lines[0] == "scene_id,im_id,obj_id,score,R,t,time"
    fields = lines[1].split(",")
    assert len(fields[4].split()) == 9 and len(fields[5].split()) == 3
    np.testing.assert_allclose([float(v) for v in fields[5].split()], 1000 * ests[0].t)
    back = read_bop_csv(path, check_name=True)
    assert len(back) == len(ests)
    for a, b in zip(ests, back):
        assert (a.scene_id, a.im_id, a.obj_id) == (b.scene_id, b.im_id, b.obj_id)
        assert a.score == b.score and a.time == b.time
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_allclose(a.t, b.t, rtol=1e-15, atol=1e-15)


def test_refuses_to_overwrite_unless_asked(tmp_path):
    path = tmp_path / "m_hope-test.csv"
    write_bop_csv(path, estimates()[:1])
    with pytest.raises(InputFileError, match="exists"):
        write_bop_csv(path, estimates())
    assert len(read_bop_csv(path)) == 1
    write_bop_csv(path, estimates(), overwrite=True)
    assert len(read_bop_csv(path)) == 5


@pytest.mark.parametrize("name", ["my_method_hope-test.csv", "method-hope-test.csv",
                                  "method_hope.csv", "method_hope-test.txt", "_hope-test.csv"])
def test_bad_names_are_refused(tmp_path, name):
    with pytest.raises(InputFileError, match="METHOD_DATASET-SPLIT"):
        write_bop_csv(tmp_path / name, estimates())
    assert not (tmp_path / name).exists()


def test_name_helpers():
    assert bop_result_filename("dope-dr50") == "dope-dr50_hope-test.csv"
    assert parse_bop_result_filename("/x/dope-dr50_hope-test.csv") == ("dope-dr50", "hope", "test", None)
    assert parse_bop_result_filename("a_hope-test-primesense.csv")[3] == "primesense"
    with pytest.raises(ValueError, match="underscore"):
        bop_result_filename("my_method")


def test_one_time_per_image_is_enforced(tmp_path):
    ests = estimates()[:2]
    ests[1].scene_id, ests[1].im_id = ests[0].scene_id, ests[0].im_id
    ests[1].time = ests[0].time + 1.0
    with pytest.raises(InputFileError, match="one time per image"):
        write_bop_csv(tmp_path / "m_hope-test.csv", ests)


def test_reader_names_the_bad_line(tmp_path):
    path = tmp_path / "m_hope-test.csv"
    write_bop_csv(path, estimates()[:2])
    lines = path.read_text().splitlines()
    lines[2] = lines[2].replace(lines[2].split(",")[5], "1 2")
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(InputFileError, match="line 3: t needs 3 numbers"):
        read_bop_csv(path)
    path.write_text("scene,im\n")
    with pytest.raises(InputFileError, match="line 1: expected the header"):
        read_bop_csv(path)


def test_non_finite_numbers_are_refused(tmp_path):
    ests = estimates()[:1]
    ests[0].t = np.array([0.0, np.nan, 1.0])
    with pytest.raises(InputFileError, match="non-finite"):
        write_bop_csv(tmp_path / "m_hope-test.csv", ests)


@pytest.mark.parametrize("R", ["-1 0 0 0 1 0 0 0 1", "0.01 0 0 0 0.01 0 0 0 0.01", "1 2 3 4 5 6 7 8 9"])
def test_an_r_that_is_no_rotation_is_refused_with_its_line(tmp_path, R):
    """The same rule as the JSON-lines reader (one owner: geometry.checked_rotation);
    the line number counts the blank line before the row."""
    path = tmp_path / "m_hope-test.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n"
                    "1,0,11,0.9,1 0 0 0 1 0 0 0 1,0 0 800,-1\n\n"
                    f"1,1,11,0.9,{R},0 0 800,-1\n")
    with pytest.raises(InputFileError, match="line 4: R: not a rotation matrix") as err:
        read_bop_csv(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_numbers_are_kept_as_written_and_unknown_time_is_allowed(tmp_path):
    """R is scored as written (a rotation to 1e-4, not re-orthonormalized) and t keeps the
    file's millimetres next to the metres, as the BOP toolkit reads them; time -1 = unknown."""
    path = tmp_path / "m_hope-test.csv"
    path.write_text("scene_id,im_id,obj_id,score,R,t,time\n"
                    "1,0,11,0.9,0.99995 0.01 0 -0.01 0.99995 0 0 0 1,0.1 -2.7 801.3,-1\n")
    (e,) = read_bop_csv(path)
    np.testing.assert_array_equal(e.R, [[0.99995, 0.01, 0], [-0.01, 0.99995, 0], [0, 0, 1]])
    np.testing.assert_array_equal(e.t_mm, [0.1, -2.7, 801.3])
    np.testing.assert_array_equal(e.t, 0.001 * np.array([0.1, -2.7, 801.3]))
    assert e.time == -1.0 and e.line == 2
