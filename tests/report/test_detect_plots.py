"""The detection pictures: built without pyplot, written atomically at the figure's size."""

import matplotlib
import numpy as np
import pytest

from oapcal.report.detect_plots import image_figure, plot_image


def test_plot_image_keeps_the_backend_and_draws_the_markers_and_crop(tmp_path):
    import cv2

    backend = matplotlib.get_backend()
    image = np.zeros((80, 120))
    image[20:40, 30:90] = 200.0
    fig = image_figure(
        image, title="t", points={"a": [[10.0, 20.0], [50.0, 60.0]]}, crop=np.array([5, 6, 100, 70])
    )
    ax = fig.axes[0]
    assert ax.get_xlim() == (5, 100) and ax.get_ylim() == (70, 6)  # y down
    assert ax.get_legend().get_texts()[0].get_text() == "a"
    np.testing.assert_array_equal(ax.lines[0].get_xydata(), [[10.0, 20.0], [50.0, 60.0]])
    plot_image(image, tmp_path / "p.png", title="t")
    assert cv2.imread(str(tmp_path / "p.png")).shape == (460, 640, 3)  # 6.4 x 4.6 in at 100 dpi
    assert matplotlib.get_backend() == backend
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.png"]  # no temporary file left


def test_plot_image_refuses_an_unknown_picture_format(tmp_path):
    with pytest.raises(ValueError):
        plot_image(np.zeros((8, 8)), tmp_path / "p.xyz", title="t")
    assert list(tmp_path.iterdir()) == []
