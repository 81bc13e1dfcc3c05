"""A seeded synthetic basis for trying samplers: the leading eigen-ABRDFs of a smooth log-ABRDF matrix.

The samplers of :mod:`btfcore.acquisition.sampling` (paper 1 (den Brok et al.)
§3.4, Alg. 1; paper 4 §4.3) choose rows of a basis ``U`` of shape
``(n_lv, k)``. Without a measured database at hand, the unit tests and
``benchmarks/bench_sampling.py`` use one and the same stand-in built here:
``n_tx`` texels, each a diffuse term plus a Blinn-Phong lobe with a tilted
normal, a random albedo and a random exponent, on the ``n_dirs x n_dirs``
light/view pairs of the UBO2014 directions, in log space as the thesis' models
are fitted (paper 1 §3.1), and its ``k`` leading left singular vectors.
"""

from __future__ import annotations

import numpy as np

from btfcore.capture.resample import lv_product, ubo2014_directions

__all__ = ["BLINN_PHONG_EXPONENTS", "synthetic_log_abrdf_basis"]

#: Range of the per-texel Blinn-Phong exponents, drawn uniformly: from broad (5) to sharp (60) highlights.
#: The unit tests used 60 and the benchmark 80 before they shared this function. 60 is kept: with 80 the
#: greedy sampler ends above 1,500 random swaps on seeds 0 and 2 of the tests' 576 x 12 problem, which the
#: tests assert against, while with 60 greedy ends below the random swap at every benchmark scale too
#: (docs/benchmarks.md, "sampling speed").
BLINN_PHONG_EXPONENTS: tuple[float, float] = (5.0, 60.0)


def synthetic_log_abrdf_basis(n_dirs: int = 24, n_tx: int = 200, k: int = 12, seed: int = 0) -> np.ndarray:
    """Orthonormal basis of a smooth synthetic log-ABRDF matrix, seeded.

    Parameters
    ----------
    n_dirs : int
        Number of UBO2014 directions used for both light and view: the matrix
        has ``n_lv = n_dirs ** 2`` rows (at most 151, 22,801 rows).
    n_tx : int
        Number of texels (ABRDF columns).
    k : int
        Number of basis vectors, ``k <= min(n_dirs ** 2, n_tx)``.
    seed : int
        Seed of the normals, albedos and exponents.

    Returns
    -------
    U : (n_dirs ** 2, k) ndarray of float64
        The ``k`` leading left singular vectors of
        :math:`B = \\log(10^{-3} + \\cos\\theta_i (\\rho + s \\cos^e\\theta_h)(1 + \\cos\\theta_o) / 2)`,
        in decreasing order of singular value; orthonormal columns.

    Notes
    -----
    ``U`` is computed by the Gram route, :math:`U_k = B V_k / \\lVert B V_k \\rVert`
    from the eigenvectors :math:`V_k` of the ``(n_tx, n_tx)`` Gram matrix
    :math:`B^T B` in float64: with ``n_tx`` much smaller than ``n_lv`` it is
    exact to rounding for the leading vectors and far faster than a full SVD at
    22,801 rows. Column signs are arbitrary; the condition numbers the samplers
    minimise do not depend on them.
    """
    if not 1 <= k <= min(n_dirs ** 2, n_tx):
        raise ValueError(f"k = {k} must lie in 1..min(n_dirs**2, n_tx) = {min(n_dirs ** 2, n_tx)}")
    rng = np.random.default_rng(seed)
    d = ubo2014_directions()[:n_dirs]
    light, view = lv_product(d, d)
    normal = np.column_stack([rng.normal(0, 0.25, (n_tx, 2)), np.ones(n_tx)])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    half = light + view
    half /= np.linalg.norm(half, axis=1, keepdims=True)
    cos_i, cos_o = np.clip(light @ normal.T, 0, None), np.clip(view @ normal.T, 0, None)
    spec = np.clip(half @ normal.T, 0, None) ** rng.uniform(*BLINN_PHONG_EXPONENTS, n_tx)
    B = np.log(1e-3 + cos_i * (rng.uniform(0.2, 0.8, n_tx) + rng.uniform(0, 1, n_tx) * spec) * (0.5 + 0.5 * cos_o))
    _, V = np.linalg.eigh(B.T @ B)                                 # (n_tx, n_tx) Gram route, ascending
    U = B @ V[:, ::-1][:, :k]
    return U / np.linalg.norm(U, axis=0)
