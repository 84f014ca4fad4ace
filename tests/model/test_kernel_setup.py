"""How the compiled kernels are set up and called: one compiled copy of each kernel per
model family (``_kernels.family_kernels``) and Numba's target set up without ``scipy.linalg``."""

from __future__ import annotations

import subprocess
import sys

import numpy as np

from paths import REPO


def _lm_inputs():
    """One small Brown-Conrady fit (k1, c_x, m free) as the arguments of ``lm_batch``."""
    from oapcal import _kernels
    from oapcal.model import BROWN_CONRADY, distort, params_from_dict, parse_model

    g = np.stack(np.meshgrid(np.linspace(-1, 1, 7), np.linspace(-1, 1, 7)), -1).reshape(-1, 2)
    truth = params_from_dict({"k1": 0.05, "c_x": 0.1, "m": 1.2})
    d = distort(g, truth)
    mask = parse_model("k1,c_x")
    p = np.where(mask, np.eye(1, 13, 12)[0], 0.0)[None].copy()
    idx = np.arange(len(g), dtype=np.int64)[None]
    counts = np.array([len(g)], dtype=np.int64)
    out = (np.zeros(1, np.int64), np.zeros(1, np.int64), np.zeros(1), np.zeros((1, 13, 13)))
    args = (g[None].copy(), d[None].copy(), idx, counts, mask[None].copy(), BROWN_CONRADY.half, p, 200,
            1e-12, 1e-12, 1e-12, None, False, *out)  # fmt: skip
    return _kernels, args, truth


def test_each_family_gets_its_own_compiled_kernels():
    kernels, args, truth = _lm_inputs()
    kernels.run_blocks(kernels.lm_batch, 1, 1, kernels.FAMILY_BC, *args)  # as fit_batch calls it
    assert args[13][0] > 0  # status: converged
    # noise-free data: the solution is the truth (k1, c_x, m; the rest fixed at 0)
    np.testing.assert_allclose(args[6][0], truth, rtol=1e-9, atol=1e-12)
    bc = kernels.family_kernels(kernels.FAMILY_BC)
    assert bc["lm_batch"].signatures  # compiled, or loaded from the cache (then without its callees)
    assert bc["lm_batch"] is not kernels.family_kernels(kernels.FAMILY_RELAY)["lm_batch"]
    assert kernels.family_kernels(kernels.FAMILY_BC) is bc  # built once per family
    # each copy is cached under its own name, so families never share a cache entry
    assert bc["lm_item"].py_func.__qualname__ == "lm_item_family0"


def test_an_eq1_session_compiles_nothing_of_the_relay():
    code = (
        "import numpy as np\n"
        "from oapcal import _kernels as k\n"
        "from oapcal.fitting import fit\n"
        "from oapcal.model import undistort\n"
        "g = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)\n"
        "r = fit(g, g * 1.1, 'k1', init='zero')\n"
        "undistort(g, r.params)\n"
        "print(r.converged, any(d.signatures for d in k.family_kernels(k.FAMILY_BC).values()), "
        "any(d.signatures for d in k.family_kernels(k.FAMILY_RELAY).values()))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    # converged; Eq. (1)'s kernels compiled or loaded; the relay's exist (built by the query), none compiled
    assert out.stdout.split() == ["True", "True", "False"], out.stdout + out.stderr


def test_kernels_set_up_numba_without_scipy_linalg():
    code = (
        "import sys\n"
        "import numpy as np\n"
        "from oapcal.fitting import fit\n"
        "g = np.stack(np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5)), -1).reshape(-1, 2)\n"
        "r = fit(g, g * 1.1, 'k1', init='zero')\n"
        "import numba.np.arraymath as a\n"
        "print(r.converged, 'scipy.linalg' in sys.modules, 'scipy.linalg.cython_blas' in sys.modules, "
        "a._HAVE_BLAS)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, check=True)
    # converged; scipy.linalg never imported (and no None left in sys.modules); BLAS flag as Numba sets it
    assert out.stdout.split() == ["True", "False", "False", "True"], out.stdout + out.stderr


def test_the_relay_kernels_cache_names_follow_the_tracers_source():
    """Numba's cache sees edits of the cached function's own file only; the relay's kernels
    contain the tracer of ``_relay_kernel.py``, so its content names their cache entries."""
    import hashlib
    from pathlib import Path

    from oapcal import _kernels, _relay_kernel

    digest = hashlib.sha256(Path(_relay_kernel.__file__).read_bytes()).hexdigest()[:10]
    relay = _kernels.family_kernels(_kernels.FAMILY_RELAY)
    assert relay["lm_item"].py_func.__qualname__ == f"lm_item_family2_{digest}"
    # Eq. (1)'s point functions live in _kernels.py itself, which Numba's cache does check
    assert _kernels.family_kernels(_kernels.FAMILY_BC)["lm_item"].py_func.__qualname__ == "lm_item_family0"
