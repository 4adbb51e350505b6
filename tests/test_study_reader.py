"""Measured data as instruments deliver them (DESIGN §6): negative depths, extra columns,
depth in mm, a BOM, an angular registration offset."""

import numpy as np
import pytest

from jaxwear._errors import InputError
from jaxwear._study import load_study, read_history, read_profile

STUDY = '''[model]
preset = "rig"
[numerics]
wear_tolerance_um = 0.02
[fit]
angle_tolerance_deg = 3
[[experiment]]
name = "e"
revolutions = 1000
clearance_mm = 0.05
angle_offset_deg = {offset}
profile = "p.csv"
'''


def test_negative_depths_are_measurements(tmp_path):
    f = tmp_path / "p.csv"
    f.write_text("angle_deg,depth_um\n0,-0.3\n90,1.5\n180,-0.1\n")
    prof = read_profile(f)
    np.testing.assert_allclose(prof.depth, [-0.3e-6, 1.5e-6, -0.1e-6])


def test_extra_columns_ignored_with_a_note(tmp_path, capsys):
    f = tmp_path / "p.csv"
    f.write_text("operator,angle_deg,depth_um,temperature_C\nA,0,1.0,21\nB,90,2.0,22\n")
    prof = read_profile(f)
    np.testing.assert_allclose(prof.depth, [1e-6, 2e-6])
    np.testing.assert_allclose(prof.angle, [0.0, np.pi / 2])
    err = capsys.readouterr().err
    assert "operator" in err and "temperature_C" in err


def test_depth_mm_column(tmp_path):
    f = tmp_path / "p.csv"
    f.write_text("angle_deg,depth_mm\n0,0.001\n90,-0.0002\n")
    np.testing.assert_allclose(read_profile(f).depth, [1e-6, -0.2e-6])
    h = tmp_path / "h.csv"
    h.write_text("hours,depth_um\n5,94\n10,130\n")
    np.testing.assert_allclose(read_history(h).depth, [94e-6, 130e-6])


def test_bom_and_crlf(tmp_path):
    (tmp_path / "p.csv").write_bytes(b"\xef\xbb\xbfangle_deg,depth_um\r\n0,1.0\r\n90,2.0\r\n")
    (tmp_path / "s.toml").write_bytes(b"\xef\xbb\xbf" + STUDY.format(offset=0).replace(
        "\n", "\r\n").encode())
    st = load_study(tmp_path / "s.toml")
    np.testing.assert_allclose(st.experiments[0].profile.depth, [1e-6, 2e-6])
    assert st.wear_tolerance_um == 0.02 and st.angle_tolerance_deg == 3


def test_angle_offset_rotates_into_bushing_frame(tmp_path):
    (tmp_path / "p.csv").write_text("angle_deg,depth_um\n0,1.0\n358,2.0\n")
    st = load_study((tmp_path / "s.toml", (tmp_path / "s.toml").write_text(
        STUDY.format(offset=5)))[0])
    np.testing.assert_allclose(np.degrees(st.experiments[0].profile.angle), [5.0, 3.0])


@pytest.mark.parametrize("text", ["angle_deg\n0\n", "depth_um,angle\n1,0\n"])
def test_missing_columns_name_line_1(tmp_path, text):
    f = tmp_path / "p.csv"
    f.write_text(text)
    with pytest.raises(InputError, match="line 1"):
        read_profile(f)
