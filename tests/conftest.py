"""Shared fixtures: seeded synthetic data sets."""

import numpy as np
import pytest

from oapcal.synthetic import synthetic_pairs


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
