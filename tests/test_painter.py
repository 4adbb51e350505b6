"""Figures drawn in a helper process (`jaxwear._report.painter`): the same bytes as drawn
here, every figure written, and a figure that fails there fails here as without the helper."""

import numpy as np
import pytest

from jaxwear._report import figures as rep
from jaxwear._report.painter import Painter

ANGLES = np.arange(64) * 360.0 / 64
DEPTH = 5.0 * np.exp(-((ANGLES - 180.0) / 30.0) ** 2)


def _profile(p, path, i):
    p.draw(path, rep.plot_profile, f"e{i}", ANGLES, DEPTH * (1 + 0.1 * i))


def test_helper_draws_the_same_bytes(tmp_path):
    here, there = tmp_path / "here", tmp_path / "there"
    here.mkdir(), there.mkdir()
    with Painter(helper=False) as p:
        for i in range(4):
            _profile(p, here / f"p{i}.png", i)
    assert p.drawn_here == 4 and p.drawn_there == 0
    with Painter(helper=True) as p:
        for i in range(4):
            _profile(p, there / f"p{i}.png", i)
    # the helper held up to two figures at a time: it drew some, this process the rest
    assert p.drawn_there >= 1 and p.drawn_here + p.drawn_there == 4
    for i in range(4):
        a, b = (here / f"p{i}.png").read_bytes(), (there / f"p{i}.png").read_bytes()
        assert a[:8] == b"\x89PNG\r\n\x1a\n" and a == b


def test_a_figure_that_fails_in_the_helper_raises_here(tmp_path):
    # a pressure map needs a 2-D array (steps x nodes): a 1-D one fails in the helper and
    # then here, where the verb's error handling sees it
    with pytest.raises(ValueError, match="not enough values"), Painter(helper=True) as p:
        p.draw(tmp_path / "bad.png", rep.plot_pressure_map, "bad", np.ones(8))
    assert not (tmp_path / "bad.png").exists()
    assert p._proc is None  # the helper was ended


def test_a_helper_that_dies_leaves_its_figures_to_this_process(tmp_path):
    with Painter(helper=True) as p:
        assert p._proc is not None
        p._proc.kill()
        p._proc.wait()
        for i in range(3):
            _profile(p, tmp_path / f"p{i}.png", i)
    assert p.drawn_here == 3 and p.drawn_there == 0
    assert all((tmp_path / f"p{i}.png").read_bytes()[:4] == b"\x89PNG" for i in range(3))


def test_an_error_in_the_verb_writes_nothing_more(tmp_path):
    with pytest.raises(RuntimeError), Painter(helper=True) as p:
        _profile(p, tmp_path / "p0.png", 0)  # sent to the helper
        raise RuntimeError("the verb failed")
    assert not (tmp_path / "p0.png").exists()
    assert p._proc is None


def test_switched_off_by_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXWEAR_FIGURE_PROCESS", "0")
    with Painter() as p:
        assert p._proc is None
        _profile(p, tmp_path / "p.png", 0)
    assert p.drawn_here == 1 and (tmp_path / "p.png").exists()
