"""The CLI's figures laid out without `tight_layout` (`_report.figures.fixed_layout`): the
left margin from the y tick labels' width must match what matplotlib's own tight_layout
chooses (the independent reference), and no label may be cut off at the figure's edge."""

import numpy as np
import pytest

from jaxwear._report.figures import fixed_layout, plt


def _figure(ymax, rows=1):
    fig, axes = plt().subplots(rows, 1, figsize=(7, 3.6 * rows), squeeze=False)
    axes = list(axes[:, 0])
    for ax in axes:
        ax.plot(np.arange(360), np.linspace(0.0, ymax, 360))
        ax.set_ylabel("wear depth [µm]")
        ax.set_xlabel("bushing angle θ [deg] (from B→D, counter-clockwise)")
        ax.set_title("n276-r10000: wear profile")
    return fig, axes


@pytest.mark.parametrize("ymax", [8.0, 250.0, 3000.0, 0.02, 123456.0, -40.0])
def test_the_left_margin_is_tight_layouts_and_cuts_nothing(ymax):
    pl = plt()
    ref, _ = _figure(ymax)
    ref.tight_layout()
    tight_in = ref.subplotpars.left * ref.get_figwidth()
    fig, axes = _figure(ymax)
    fixed_layout(fig, axes, right=0.96, top=0.9, bottom=0.165)
    fixed_in = fig.subplotpars.left * fig.get_figwidth()
    assert abs(fixed_in - tight_in) < 0.1, (fixed_in, tight_in)
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    for ax in axes:
        texts = [t for t in (*ax.get_yticklabels(), ax.yaxis.label)
                 if t.get_visible() and t.get_text()]
        assert texts
        for t in texts:
            box = t.get_window_extent(renderer)
            assert box.x0 >= 0, (t.get_text(), box)
    pl.close(ref)
    pl.close(fig)


def test_a_column_of_axes_takes_its_widest_labels():
    """Two stacked axes (the load figure): the margin fits the wider axis's labels."""
    fig, axes = _figure(1.0, rows=2)
    axes[1].set_ylim(0, 25000)
    fixed_layout(fig, axes, right=0.98, top=0.93, bottom=0.115, hspace=0.11)
    one, _ = _figure(1.0)
    fixed_layout(one, one.axes, right=0.98, top=0.93, bottom=0.115)
    assert fig.subplotpars.left > one.subplotpars.left
    plt().close(fig)
    plt().close(one)
