"""Headless napari for the plugin's tests.

napari draws with OpenGL; Qt's ``offscreen`` platform has an OpenGL context only through an
X display, so without ``DISPLAY`` a virtual one is started with Xvfb (installed by
``scripts/ensure-qt-libs.sh``, which ``bash scripts/run.sh test`` runs).  Without napari (the
``napari`` extra) or Xvfb the tests skip and say why.
"""

import os
import shutil
import subprocess

import numpy as np
import pytest

HAVE_NAPARI = True
try:  # the extra installed? (napari's own pytest plugin then provides make_napari_viewer)
    import magicgui  # noqa: F401
    import napari  # noqa: F401
    import pytestqt  # noqa: F401
except ImportError:
    HAVE_NAPARI = False


def pytest_collection_modifyitems(config, items):
    # one pytest-xdist worker runs every napari test (``--dist loadgroup``): they share the
    # session's display and napari's settings, and one Qt application per process is enough
    group = pytest.mark.xdist_group("napari")
    for item in items:
        if "napari_plugin" in str(item.fspath):
            item.add_marker(group)
    if HAVE_NAPARI:
        return
    skip = pytest.mark.skip(reason="the napari extra is not installed (pip install -e '.[napari]')")
    for item in items:
        if "napari_plugin" in str(item.fspath):
            item.add_marker(skip)


#: Starts Xvfb ($0) on a free display written to fd $1, and a watchdog that stops it once the
#: test process ($2) has ended: Qt stays connected to the display until the process exits,
#: and a server stopped under it makes Xlib end the process with status 1.
_START_XVFB = (
    '( "$0" -displayfd "$1" -screen 0 1600x1200x24 -nolisten tcp & x=$!; '
    'while kill -0 "$2" 2>/dev/null; do sleep 1; done; kill "$x" ) >/dev/null 2>&1 &'
)


@pytest.fixture(scope="session")
def display():
    """An X display for Qt's offscreen platform: ``DISPLAY`` if set, else a private Xvfb
    that ends with the test process."""
    os.environ["QT_QPA_PLATFORM"] = "offscreen"
    if os.environ.get("DISPLAY"):
        return os.environ["DISPLAY"]
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        pytest.skip(
            "Xvfb is not installed (bash scripts/ensure-qt-libs.sh installs it): napari needs an "
            "OpenGL context, which Qt's offscreen platform gets only through an X display"
        )
    read_fd, write_fd = os.pipe()
    args = ["sh", "-c", _START_XVFB, xvfb, str(write_fd), str(os.getpid())]
    subprocess.run(args, pass_fds=(write_fd,), check=True, stdin=subprocess.DEVNULL)
    os.close(write_fd)
    with os.fdopen(read_fd) as fh:
        number = fh.readline().strip()
    if not number:
        pytest.skip("Xvfb did not start (no display number); the napari tests need an X display")
    os.environ["DISPLAY"] = f":{number}"
    return os.environ["DISPLAY"]


@pytest.fixture
def viewer(display, make_napari_viewer):
    """A napari viewer (not shown) with a window large enough for screenshots."""
    v = make_napari_viewer()
    v.window._qt_window.resize(1400, 900)
    return v


@pytest.fixture
def wait(qtbot):
    """Wait until a widget's thread worker has finished (at most ``timeout`` s)."""

    def run(widget, timeout=120):
        qtbot.waitUntil(lambda: not widget.busy, timeout=int(timeout * 1000))

    return run


@pytest.fixture(scope="session")
def demo():
    """The plugin's sample image (the demo's simulated camera image) and its truth."""
    from oapcal.napari_plugin._sample import demo_image

    image, kwargs = demo_image()[0]
    truth = kwargs["metadata"]["oapcal_truth"]
    visible = np.asarray(truth["visible"], bool)
    return {
        "image": image,
        "kwargs": kwargs,
        "ids": [i for i, v in zip(truth["ids"], visible) if v],
        "xy_u": np.asarray(truth["xy_u"])[visible],
        "xy_d": np.asarray(truth["xy_d"])[visible],
        "um_per_px": truth["um_per_px"],
    }


@pytest.fixture
def truth_layers(demo):
    """Add the demo's true corners as ``distorted`` / ``reference`` points layers to a viewer,
    the distorted ones with Gaussian noise of ``noise`` px (seeded); returns them."""
    from oapcal.napari_plugin._layers import points_layers

    def add(viewer, noise=0.0, seed=0):
        rng = np.random.default_rng(seed)
        xy_d = demo["xy_d"] + rng.normal(0, noise, demo["xy_d"].shape) if noise else demo["xy_d"]
        for data, kwargs, kind in points_layers(demo["xy_u"], xy_d, demo["ids"], um_per_px=demo["um_per_px"]):
            getattr(viewer, f"add_{kind}")(data, **kwargs)
        return xy_d

    return add
