"""Shared fixtures: seeded synthetic data sets; the kernels compiled in the background when
the cache is empty (:mod:`kernel_warmup`)."""

import numpy as np
import pytest

from oapcal.synthetic import synthetic_pairs


def pytest_sessionstart(session):
    import kernel_warmup

    session.config._oapcal_warmup = kernel_warmup.start()


def pytest_sessionfinish(session, exitstatus):
    import kernel_warmup

    kernel_warmup.stop(getattr(session.config, "_oapcal_warmup", None))


@pytest.fixture
def pairs():
    """About 250 pairs over 640x480 px, ~40 px distortion, 0.3 px noise (seeded)."""
    return synthetic_pairs(seed=11)


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


@pytest.fixture
def run_cli(capsys):
    """Run ``oapcal`` in-process; returns (exit code, stdout, stderr)."""
    from oapcal.cli import main

    def run(*args):
        code = main([str(a) for a in args])
        out, err = capsys.readouterr()
        return code, out, err

    return run
