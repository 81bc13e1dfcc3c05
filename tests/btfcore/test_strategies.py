"""The acquisition evaluation's strategy builders (btfcore.acquisition.strategies)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from btfcore import ILL_CONDITIONED_SOLVE
from btfcore.acquisition import strategies


def test_builders_report_an_ill_conditioned_operator_instead_of_warning():
    # pyproject turns BtfWarning into an error: a builder that warned would fail here. The evaluation reports
    # the condition number (its `ill-conditioned` flag, docs/evaluation.md), so a worker's log must not repeat it.
    rng = np.random.default_rng(0)
    U = rng.normal(size=(40, 3)) * [1.0, 1.0, 1e-8]
    U[0, 2] = 1.0                                                     # the third vector lives on row 0 only
    basis = SimpleNamespace(U=U, sigma=np.ones(3))
    rows = np.arange(1, 40)                                           # row 0 not measured: kappa ~ 1e8
    variance = np.ones(40)
    variance[0] = 100.0                                               # thresholded drops row 0
    design = SimpleNamespace(bases=SimpleNamespace(als=basis, linear=SimpleNamespace(U=rng.normal(size=(40, 2))
                                                                                      * [1.0, 1e-7])),
                             sparse=lambda n: (rows, None), n_pairs=2376, variance=variance)
    _, ops, info = strategies._sparse_pinv(design, 100)
    assert info["condition"] == ops["rgb"].condition > ILL_CONDITIONED_SOLVE
    _, ops, info = strategies._thresholded(design, None)
    assert info["condition"] == ops["rgb"].condition > ILL_CONDITIONED_SOLVE
