"""Measured data as instruments deliver them (design.md §6): negative depths, extra columns,
depth in mm, a BOM, an angular registration offset."""

import numpy as np
import pytest

from jaxwear._core.errors import InputError
from jaxwear._study.study import load_study, read_history, read_profile

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


# ---------------------------------------------- raw scans and the noise-level warning

def _scan_study(tmp_path, csv_text, name="p.csv"):
    (tmp_path / name).write_text(csv_text)
    (tmp_path / "s.toml").write_text(STUDY.format(offset=0).replace("p.csv", name))
    return tmp_path / "s.toml"


def test_two_raw_scans_give_depth_after_minus_before(tmp_path):
    """Wear opens the bore: the radius after the test minus the radius before is the depth
    into the layer (hand values)."""
    st = load_study(_scan_study(
        tmp_path, "angle_deg,radius_before_um,radius_after_um,revolutions\n"
                  "0,7480.10,7481.60,1000\n90,7480.30,7480.20,1000\n180,7479.9,7482.4,500\n"))
    prof = st.experiments[0].profile
    np.testing.assert_allclose(prof.depth * 1e6, [1.5, -0.1, 2.5], atol=1e-9)
    np.testing.assert_allclose(prof.revolutions, [1000, 1000, 500])
    # without the revolutions column every row is the experiment's final profile
    st = load_study(_scan_study(tmp_path, "angle_deg,radius_before_um,radius_after_um\n"
                                          "10,7480.0,7480.5\n", name="q.csv"))
    assert st.experiments[0].profile.revolutions.tolist() == [1000.0]


@pytest.mark.parametrize("text, where", [
    ("angle_deg,depth_um,radius_before_um,radius_after_um\n0,1,2,3\n", "line 1"),
    ("angle_deg,radius_before_um\n0,7480\n", "line 1"),
    ("angle_deg,radius_after_um,radius_before_um\n0,7480,x\n", "line 2"),
    ("angle_deg,radius_before_um,radius_after_um\n0,7480,7481\n10,7480\n", "line 3"),
    ("angle_deg,radius_before_um,radius_after_um\n400,7480,7481\n", "line 2"),
    ("angle_deg,radius_before_um,radius_after_um,revolutions\n0,7480,7481,-5\n", "line 2"),
    ("angle_deg,radius_before_um,radius_after_um\n0,7480,nan\n", "line 2"),
])
def test_malformed_raw_scans_exit_2_naming_file_and_line(tmp_path, text, where, capsys):
    from jaxwear.cli import main

    study = _scan_study(tmp_path, text)
    with pytest.raises(InputError, match=f"p.csv: {where}"):
        load_study(study)
    assert main(["calibrate", str(study), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "p.csv" in err and where in err and "Traceback" not in err


def _noisy_scan(rng, sigma=0.3):
    a = np.arange(0.0, 360.0, 2.0)
    d = 6.0 * np.exp(-0.5 * ((a - 200.0) / 25.0) ** 2) + sigma * rng.standard_normal(len(a))
    return a, d


def test_robust_noise_level_of_a_scan():
    """σ from neighbour differences (the one estimator, `_noise`), unaffected by the scar
    and by a few outliers (their differences lie beyond 3.5 robust SDs and are dropped)."""
    from jaxwear._core.noise import profile_noise as robust_noise

    rng = np.random.default_rng(3)
    est, est_out = [], []
    for _ in range(20):
        a, d = _noisy_scan(rng)
        est.append(robust_noise(a, d, np.full(len(a), 1000.0)))
        d[::60] += 8.0  # 3 outliers touch 9 of 180 differences, all beyond the cut
        est_out.append(robust_noise(a, d, np.full(len(a), 1000.0)))
    assert np.mean(est) == pytest.approx(0.3, rel=0.04)
    assert np.mean(est_out) == pytest.approx(0.3, rel=0.05)


def test_depth_far_below_zero_warns_on_one_line(tmp_path, capsys):
    rng = np.random.default_rng(4)
    a, d = _noisy_scan(rng)
    body = "".join(f"{x:g},{y:.4f}\n" for x, y in zip(a, d))
    read_profile(_write(tmp_path / "ok.csv", "angle_deg,depth_um\n" + body))
    assert (d < 0).sum() > 20 and capsys.readouterr().err == ""  # plain noise: silent
    d[50] = -4.0  # > 10 noise levels below zero: an offset or sign error in the scan
    body = "".join(f"{x:g},{y:.4f}\n" for x, y in zip(a, d))
    prof = read_profile(_write(tmp_path / "bad.csv", "angle_deg,depth_um\n" + body))
    assert prof.depth[50] == pytest.approx(-4e-6)  # kept: a warning, not an error
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("warning:") and "bad.csv" in err[0]
    assert "line 52" in err[0]


def _write(path, text):
    path.write_text(text)
    return path
