"""Load files (issue 28, `preset = "load_history"`): fuzzed files and what multibody
programs write; each bad input refused by line and column, with nothing written."""

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_bad_inputs import _main, _refused
from test_fuzz_inputs import (
    HISTORY_ROWS,
    SETTINGS,
    _csv,
    _load_or_input_error,
    _run_verb,
    _store,
    csv_texts,
    dump_toml,
    encodings,
    mutated_docs,
)

from jaxwear import load_study

# ------------------------------------------------------------------ load files (issue 28)

def _load_rows(n=12, turn_deg=0.0):
    """One period of a swinging pin, n rows over 6 s: time_s,load_x_N,load_y_N,angle_deg."""
    t = np.arange(n) * (6.0 / n)
    phi = 30.0 * np.sin(2 * np.pi * t / 6.0) + turn_deg * t / 6.0
    mag = 8000.0 + 2000.0 * np.cos(2 * np.pi * t / 6.0)
    th = np.radians(90.0 - phi)
    return [(round(float(a), 6), round(float(m * np.cos(b)), 6),
             round(float(m * np.sin(b)), 6), round(float(c), 6))
            for a, m, b, c in zip(t, mag, th, phi)]


LOAD_COLUMNS = ["time_s", "load_x_N", "load_y_N", "angle_deg"]
LOAD_ROWS = _load_rows()
BASE_LOAD = {
    "model": {"preset": "load_history", "load_history": "l.csv",
              "parameters": {"K_d_per_Pa": 1.0e-14, "width_mm": 28.0}},
    "numerics": {"nodes": 48, "steps_per_rev": 48},
    "experiment": [{"name": "a", "hours": 10, "clearance_mm": 0.05, "history": "h.csv"},
                   {"name": "b", "cycles": 3000, "clearance_mm": 0.1}],
}
LOAD_VERBS = ["simulate", "calibrate", "diagnose", "sensitivity", "sweep", "synth"]


def _load_study(folder: Path, rows=LOAD_ROWS, text=None, doc=None):
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "l.csv").write_text(text if text is not None else _csv(LOAD_COLUMNS, rows))
    (folder / "h.csv").write_text(_csv(["hours", "depth_mm"], HISTORY_ROWS))
    (folder / "study.toml").write_text(dump_toml(doc or BASE_LOAD))
    return folder / "study.toml"


@SETTINGS
@given(doc=mutated_docs(BASE_LOAD), enc=encodings(), verb=st.sampled_from(LOAD_VERBS))
def test_fuzzed_load_history_study(tmp_path_factory, engines_stubbed, doc, enc, verb):
    d = tmp_path_factory.mktemp("lh")
    _load_study(d, doc=doc)
    _store(d / "study.toml", dump_toml(doc), enc)
    _load_or_input_error(d, ["study.toml", "l.csv", "h.csv"])
    _run_verb(verb, d, ["study.toml", "l.csv", "h.csv"])


@SETTINGS
@given(text=csv_texts(LOAD_COLUMNS, LOAD_ROWS), enc=encodings(),
       verb=st.sampled_from(LOAD_VERBS))
def test_fuzzed_load_csv(tmp_path_factory, engines_stubbed, text, enc, verb):
    """A mutated load file loads (and then holds the rows it says) or is refused naming the
    file (a cell that breaks the order of time, the closing of the ends, or a number)."""
    d = tmp_path_factory.mktemp("l")
    _load_study(d)
    _store(d / "l.csv", text, enc)
    study = _load_or_input_error(d, ["l.csv", "study.toml"])
    if study is not None:  # loaded: the cycle holds the file's rows, in order
        cyc = study.config.duty_cycle[0].load
        assert np.all(np.diff(cyc.time) > 0) and cyc.period > cyc.time[-1]
        assert np.all(np.isfinite(cyc.force)) and np.all(np.isfinite(cyc.angle))
    _run_verb(verb, d, ["l.csv", "study.toml"])


@SETTINGS
@given(enc=encodings(), blank=st.booleans(), extra=st.booleans(),
       shift=st.sampled_from([0.0, 12.5, -3.0]), turns=st.sampled_from([0, 1, -2]))
def test_what_multibody_programs_write_loads_as_meant(tmp_path_factory, enc, blank, extra,
                                                      shift, turns):
    """BOM, CRLF, blank lines, an extra column, a first time other than 0, and a pin that
    turns whole revolutions (a crank bearing, angles unwrapped or wrapped to ±180°) load as
    the same cycle: times from 0, the period 6 s, the rotation per period by hand."""
    rows = _load_rows(turn_deg=360.0 * turns)
    rows = [(t + shift, fx, fy, (a + 180.0) % 360.0 - 180.0 if turns else a)
            for t, fx, fy, a in rows]
    header = LOAD_COLUMNS + (["note"] if extra else [])
    text = _csv(header, [r + (("x",) if extra else ()) for r in rows])
    if blank:
        text = text.replace("\n", "\n\n", 3)
    d = tmp_path_factory.mktemp("okl")
    _load_study(d)
    _store(d / "l.csv", text, enc)
    cyc = load_study(d / "study.toml").config.duty_cycle[0].load
    assert cyc.period == pytest.approx(6.0, rel=1e-9) and cyc.time[0] == 0.0
    np.testing.assert_allclose(cyc.time, np.arange(12) * 0.5, atol=1e-9)
    want = [r[1:3] for r in _load_rows(turn_deg=360.0 * turns)]
    np.testing.assert_allclose(cyc.force, want, atol=1e-9)
    phi = np.array([r[3] for r in _load_rows(turn_deg=360.0 * turns)])
    steps = np.diff(np.r_[phi, phi[0] + 360.0 * turns])
    assert cyc.rotation == pytest.approx(np.radians(np.abs(steps).sum()), rel=1e-9)
    assert cyc.angle[-1] - cyc.angle[0] == pytest.approx(np.radians(360.0 * turns), abs=1e-9)


def _refused_nothing_written(study, *must):
    out = study.parent / "out"
    line = _refused(["simulate", study, "--out", out], *must)
    assert not out.exists(), "a refused run wrote something"
    return line


def test_load_file_ends_that_do_not_close_are_refused(tmp_path, engines_stubbed):
    rows = LOAD_ROWS[:8]  # two thirds of the period: the last row is far from the first
    line = _refused_nothing_written(_load_study(tmp_path, rows), "l.csv", "line 9",
                                    "column", "do not close", "2 x the largest change",
                                    "near the end")
    assert any(f"({c})" in line for c in LOAD_COLUMNS[1:]), line
    # the load alone: the angle closes, load_x drifts by 20 kN over the file (an export
    # whose end is another state than its start), despite an impact spike mid-file
    rows = [(r[0], r[1] + 20000.0 * r[0] / 6.0 + (20000.0 if i == 5 else 0.0), r[2], r[3])
            for i, r in enumerate(LOAD_ROWS)]
    _refused_nothing_written(_load_study(tmp_path / "x", rows), "l.csv", "line 13",
                             "column 2 (load_x_N)", "do not close")


def test_load_file_time_not_increasing_is_refused(tmp_path, engines_stubbed):
    rows = list(LOAD_ROWS)
    rows[4] = (rows[3][0],) + rows[4][1:]  # line 6 repeats line 5's time
    _refused_nothing_written(_load_study(tmp_path, rows), "l.csv", "line 6",
                             "column 1 (time_s)", "increasing")


@pytest.mark.parametrize("cell,what", [("nan", "NaN"), ("1e999", "NaN/inf"),
                                       ("12,5", "values"), ("x", "column 3 (load_y_N)")])
def test_load_file_bad_numbers_name_line_and_column(tmp_path, engines_stubbed, cell, what):
    text = _csv(LOAD_COLUMNS, LOAD_ROWS).splitlines()
    cells = text[3].split(",")
    cells[2] = cell
    text[3] = ",".join(cells)
    _refused_nothing_written(_load_study(tmp_path, text="\n".join(text) + "\n"), "l.csv",
                             "line 4", what)


def test_load_file_of_one_row_and_missing_columns_are_refused(tmp_path, engines_stubbed):
    _refused_nothing_written(_load_study(tmp_path, LOAD_ROWS[:1]), "l.csv", "one row is no "
                             "period")
    text = _csv(LOAD_COLUMNS[:3], [r[:3] for r in LOAD_ROWS])
    _refused_nothing_written(_load_study(tmp_path / "m", text=text), "l.csv", "line 1",
                             "'angle_deg' missing", "time_s,load_x_N,load_y_N,angle_deg")


def test_load_file_in_radians_is_refused_or_warned(tmp_path, engines_stubbed):
    """A full turn in radians (6.28 under angle_deg) cannot close in degrees: refused,
    naming radians. A swing in radians (±0.52) reads as a ±0.52° oscillation: a warning."""
    rows = [(t, fx, fy, float(np.radians(a))) for t, fx, fy, a in _load_rows(turn_deg=360.0)]
    _refused_nothing_written(_load_study(tmp_path, rows), "l.csv", "column 4 (angle_deg)",
                             "radians", "1 x 2π")
    rows = [(t, fx, fy, float(np.radians(a))) for t, fx, fy, a in LOAD_ROWS]
    rc, err = _main(["simulate", _load_study(tmp_path / "w", rows), "--out", tmp_path / "o"])
    assert rc == "loaded", err
    warn = [w for w in err.splitlines() if w.startswith("warning:")]
    assert len(warn) == 1 and "l.csv" in warn[0] and "radians" in warn[0], err
    rc, err = _main(["simulate", _load_study(tmp_path / "deg"), "--out", tmp_path / "o"])
    assert rc == "loaded" and "warning" not in err, err


def test_load_in_kilonewtons_warns(tmp_path, engines_stubbed):
    """8 kN written as 8 "N" on a 15 x 28 mm bore is 0.02 MPa: a warning naming kN, once."""
    rows = [(t, fx / 1e3, fy / 1e3, a) for t, fx, fy, a in LOAD_ROWS]
    rc, err = _main(["simulate", _load_study(tmp_path, rows), "--out", tmp_path / "o"])
    assert rc == "loaded", err
    warn = [w for w in err.splitlines() if w.startswith("warning:")]
    assert len(warn) == 1 and "kN" in warn[0] and "l.csv" in warn[0], err
    assert "0.0238 MPa" in warn[0]  # 10 kN peak / (15 mm x 28 mm), by hand: 0.0238 MPa


def test_load_file_whose_last_row_repeats_the_first_warns(tmp_path, engines_stubbed):
    rows = [*LOAD_ROWS, (6.0, *LOAD_ROWS[0][1:])]
    rc, err = _main(["simulate", _load_study(tmp_path, rows), "--out", tmp_path / "o"])
    assert rc == "loaded", err
    assert "line 14 equals the first row" in err and "6.5 s" in err, err


@pytest.mark.parametrize("change,must", [
    (lambda d: d["model"]["parameters"].update(speed_rpm=100), ["speed_rpm", "does not enter"]),
    (lambda d: d["experiment"][0].update(cycles=100), ["'hours' or 'cycles', not both"]),
    (lambda d: d["model"].update(duty_cycle=[]), ["one of the two"]),
    (lambda d: d["model"].update(load_history="nope.csv"), ["nope.csv", "not found"]),
    (lambda d: (d["model"].pop("load_history"), d["model"].update(duty_cycle=[
        {"load_history": "l.csv", "duration_h": 0}])), ["duration_h", "> 0"]),
    (lambda d: d["model"].update(preset="rig"), ["load_history", "preset"]),
], ids=["mechanism-key", "hours-and-cycles", "both-forms", "missing-file", "zero-duration",
        "not-this-preset"])
def test_load_history_study_mistakes_are_refused(tmp_path, engines_stubbed, change, must):
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    change(doc)
    _refused_nothing_written(_load_study(tmp_path, doc=doc), "study.toml", *must)


def test_cycles_count_periods_through_the_duty_cycle(tmp_path):
    """`cycles` = periods of the files in the duty cycle's order: 1 h of a 6 s file (600
    cycles) then 4 h of a 12 s file (1200): 600 + 600 cycles = 1 h + 2 h, by hand."""
    import copy

    slow = [(2 * t, fx, fy, a) for t, fx, fy, a in LOAD_ROWS]
    doc = copy.deepcopy(BASE_LOAD)
    del doc["model"]["load_history"]
    doc["model"]["duty_cycle"] = [{"load_history": "l.csv", "duration_h": 1.0},
                                  {"load_history": "s.csv", "duration_h": 4.0}]
    doc["experiment"][1]["cycles"] = 1200
    study = _load_study(tmp_path, doc=doc)
    (tmp_path / "s.csv").write_text(_csv(LOAD_COLUMNS, slow))
    st_ = load_study(study)
    assert st_.experiments[1].hours == pytest.approx(3.0, rel=1e-12)
    assert [b.load.period for b in st_.config.duty_cycle] == pytest.approx([6.0, 12.0])


def test_simulate_never_writes_over_a_load_file(tmp_path, engines_stubbed):
    """`simulate --out` beside the study writes load_EXP.csv: where that is the study's own
    load file (experiment "a", file load_a.csv), it is refused before any work."""
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    doc["model"]["load_history"] = "load_a.csv"
    study = _load_study(tmp_path, doc=doc)
    (tmp_path / "load_a.csv").write_text(_csv(LOAD_COLUMNS, LOAD_ROWS))
    before = (tmp_path / "load_a.csv").read_text()
    _refused(["simulate", study, "--out", tmp_path], "load_a.csv",
             "refusing to replace an input")
    assert (tmp_path / "load_a.csv").read_text() == before


# ------------------------------------------------------------------ issue 41: load files


def _scaled(rows, factor):
    return [(t, fx * factor, fy * factor, a) for t, fx, fy, a in rows]


def test_a_load_file_that_never_loads_or_never_turns_is_refused(tmp_path, engines_stubbed):
    """All-zero loads, one angle on every row, or a file of two equal rows ran to exit 0
    with depths of exactly 0 and no word (issue 41): nothing can wear (no pressure; no
    sliding, Archard wear K_d p dS = 0), so each is refused, naming the file and column."""
    zero = [(t, 0.0, 0.0, a) for t, _, _, a in LOAD_ROWS]
    _refused_nothing_written(_load_study(tmp_path / "z", zero), "l.csv", "load_x_N",
                             "every row is 0 N", "never loaded")
    still = [(t, fx, fy, 12.0) for t, fx, fy, _ in LOAD_ROWS]
    _refused_nothing_written(_load_study(tmp_path / "s", still), "l.csv",
                             "column 4 (angle_deg)", "same angle", "no sliding")
    two = [(0.0, 8000.0, 100.0, 0.0), (1.0, 8000.0, 100.0, 0.0)]
    _refused_nothing_written(_load_study(tmp_path / "t", two), "l.csv", "same angle")


def test_a_still_joint_with_creep_on_warns(tmp_path, engines_stubbed):
    """Creep wears without sliding: a still joint is then a study, with a warning."""
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    doc["model"]["effects"] = ["creep"]
    still = [(t, fx, fy, 12.0) for t, fx, fy, _ in LOAD_ROWS]
    rc, err = _main(["simulate", _load_study(tmp_path, still, doc=doc), "--out",
                     tmp_path / "o"])
    assert rc == "loaded", err
    assert "warning" in err and "only the effects switched on (creep) can wear" in err, err


def test_a_folder_as_the_load_file_is_called_a_folder(tmp_path, engines_stubbed):
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    doc["model"]["load_history"] = "loads"
    study = _load_study(tmp_path, doc=doc)
    (tmp_path / "loads").mkdir()
    line = _refused_nothing_written(study, "model.load_history", "'loads' is a folder",
                                    "expected a load file")
    assert "not found" not in line


@pytest.mark.parametrize("cycles,must", [(0.5, "cycles = 0.5"), (1e15, "cycles = 1e+15")])
def test_cycles_out_of_range_name_cycles_as_written(tmp_path, engines_stubbed, cycles, must):
    """`cycles = 0.5` blamed `hours` (which the study does not set); `cycles = 1e15` named
    the hours it converts to (1.67e12 h)."""
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    doc["experiment"][1]["cycles"] = cycles
    line = _refused_nothing_written(_load_study(tmp_path, doc=doc), "study.toml",
                                    "experiment 'b'.cycles", must, "[1, 1e+12]")
    assert "hours" not in line


def test_a_history_past_the_cycles_names_cycles(tmp_path, engines_stubbed):
    import copy

    doc = copy.deepcopy(BASE_LOAD)
    del doc["experiment"][0]["hours"]
    doc["experiment"][0]["cycles"] = 3000  # 5 h of the 6 s file; the history goes to 10 h
    line = _refused_nothing_written(_load_study(tmp_path, doc=doc), "experiment 'a'",
                                    "history goes to 10 h", "cycles = 3000, 5 h")
    assert "> hours" not in line


def test_a_load_beyond_the_layer_blames_the_file_not_load_scale(tmp_path, engines_stubbed):
    """Loads of 1e12 N blamed `load_scale = 1`, a key the study does not set: the file's
    numbers carry the load, so the file, its columns and the peak row are named."""
    peak = max(float(np.hypot(fx, fy)) for _, fx, fy, _ in LOAD_ROWS)
    rows = _scaled(LOAD_ROWS, 1e12 / peak)
    line = _refused_nothing_written(_load_study(tmp_path, rows), "l.csv", "data row 1",
                                    "(load_x_N, load_y_N)", "1e+12 N", "strain",
                                    "in newtons")
    assert "load_scale" not in line


def test_a_load_too_light_to_indent_the_layer_is_refused(tmp_path, engines_stubbed):
    """0.01 N on the 15 x 28 mm bore (24 Pa) ended in exit 1 'contact solve did not
    converge ... please report': the indentation is 5e-5 of the clearance. Refused before
    any work, naming the file; 10.9 N (indentation 5.5e-3 of it) is run."""
    peak = max(float(np.hypot(fx, fy)) for _, fx, fy, _ in LOAD_ROWS)
    _refused_nothing_written(_load_study(tmp_path / "t", _scaled(LOAD_ROWS, 0.01 / peak)),
                             "l.csv", "0.01 N", "of the clearance", "in newtons")
    rc, err = _main(["simulate", _load_study(tmp_path / "l", _scaled(LOAD_ROWS, 10.9 / peak)),
                     "--out", tmp_path / "o"])
    assert rc == "loaded", err
