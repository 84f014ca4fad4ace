"""How the compiled kernels are set up and called: the family code as a compile-time
constant (``_kernels.FamilyCode``) and Numba's target set up without ``scipy.linalg``."""

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


def test_family_code_reaches_the_kernels_as_a_compile_time_constant():
    kernels, args, truth = _lm_inputs()
    kernels.run_blocks(kernels.lm_batch, 1, 1, 0, *args)  # as fit_batch calls it
    families = {str(sig[2]) for sig in kernels.lm_batch.signatures}
    assert "Literal[int](0)" in families
    assert args[13][0] > 0  # status: converged
    # noise-free data: the solution is the truth (k1, c_x, m; the rest fixed at 0)
    np.testing.assert_allclose(args[6][0], truth, rtol=1e-9, atol=1e-12)


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
