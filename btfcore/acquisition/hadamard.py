"""Hadamard S-matrices for illumination multiplexing.

An S-matrix of order ``n`` is an ``n x n`` binary matrix whose rows are the
illumination patterns of a multiplexed capture: each pattern switches on
``(n + 1) / 2`` of ``n`` lights, and the patterns are the least-squares optimal
binary designs for signal-independent noise (Harwit & Sloane 1979). The thesis
(papers 2-3, "Multiplexed acquisition" 3.3) builds them with the *quadratic
residue construction*, which exists for prime orders ``n = 3 (mod 4)``; a dome
whose light count is not such a prime uses the next valid order and truncates
the columns (198 LEDs -> order 199).

References
----------
.. [1] M. Harwit and N. J. A. Sloane, *Hadamard Transform Optics*,
   Academic Press, 1979, ch. 2-3.
.. [2] Y. Y. Schechner, S. K. Nayar and P. N. Belhumeur, "A theory of
   multiplexed illumination", ICCV 2003.
.. [3] The thesis, App. "Multiplexed acquisition" 3.1: quadratic residue
   construction, truncation to the number of light sources.
"""

from __future__ import annotations

import numpy as np

__all__ = ["is_s_matrix_order", "multiplexing_patterns", "s_matrix", "smallest_s_matrix_order"]


def _is_prime(n: int) -> bool:
    if n < 2:
        return False
    if n % 2 == 0:
        return n == 2
    f = 3
    while f * f <= n:
        if n % f == 0:
            return False
        f += 2
    return True


def is_s_matrix_order(n: int) -> bool:
    """Whether the quadratic residue construction gives an S-matrix of order ``n``.

    Parameters
    ----------
    n : int
        Candidate order.

    Returns
    -------
    valid : bool
        True when ``n`` is prime and ``n % 4 == 3``.
    """
    return isinstance(n, (int, np.integer)) and int(n) % 4 == 3 and _is_prime(int(n))


def _nearest_orders(n: int) -> tuple[int | None, int]:
    below = next((m for m in range(int(n) - 1, 2, -1) if is_s_matrix_order(m)), None)
    above = next(m for m in range(max(int(n) + 1, 3), 10 * max(int(n), 3) + 100) if is_s_matrix_order(m))
    return below, above


def s_matrix(n: int) -> np.ndarray:
    """S-matrix of order ``n`` by the quadratic residue construction.

    Parameters
    ----------
    n : int
        Order: a prime with ``n % 4 == 3`` (3, 7, 11, 19, 23, 31, 43, 47, ...).

    Returns
    -------
    S : (n, n) ndarray of uint8
        Binary matrix, row ``i`` is illumination pattern ``i``, column ``j`` is
        light ``j``.

    Raises
    ------
    ValueError
        If ``n`` is not a prime of the form ``4p + 3``; the message names the
        nearest valid orders below and above.

    Notes
    -----
    Let :math:`Q = \\{k^2 \\bmod n : k = 0, \\dots, (n-1)/2\\}` be the quadratic
    residues of :math:`0, \\dots, (n-1)/2` modulo :math:`n` (zero included, so
    :math:`|Q| = (n+1)/2`). The first row is

    .. math:: s_{0j} = 1 \\text{ if } j \\in Q \\text{ else } 0,

    and row :math:`i` is row 0 cyclically shifted left by :math:`i`:
    :math:`s_{ij} = s_{0,(i+j) \\bmod n}`. Because :math:`Q` is a cyclic
    :math:`(n, (n+1)/2, (n+1)/4)` difference set when :math:`n \\equiv 3 \\pmod 4`,

    .. math:: S^T S = \\tfrac{n+1}{4} (I + J), \\qquad
              S^{-1} = \\tfrac{2}{n+1} (2 S^T - J),

    with :math:`J` the all-ones matrix: every pattern has :math:`(n+1)/2` lights
    on, every light is on in :math:`(n+1)/2` patterns and any two lights share
    :math:`(n+1)/4` patterns.

    References
    ----------
    .. [1] Harwit & Sloane (1979), *Hadamard Transform Optics*, sec. 3.
    .. [2] Thesis, App. "Multiplexed acquisition", 3.1.

    Examples
    --------
    >>> s_matrix(3)
    array([[1, 1, 0],
           [1, 0, 1],
           [0, 1, 1]], dtype=uint8)
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)):
        raise ValueError(f"S-matrix order must be an integer, got {n!r}")
    n = int(n)
    if not is_s_matrix_order(n):
        below, above = _nearest_orders(n)
        near = f"{below} or {above}" if below is not None else f"{above}"
        why = "is not prime" if not _is_prime(n) else f"is prime but {n} % 4 == {n % 4}, not 3"
        raise ValueError(
            f"no quadratic-residue S-matrix of order {n}: {n} {why}; the order must be a prime "
            f"with n % 4 == 3; nearest valid orders: {near} (use smallest_s_matrix_order(n_leds) "
            f"and truncate the columns, as multiplexing_patterns does)"
        )
    k = np.arange((n - 1) // 2 + 1, dtype=np.int64)
    row = np.zeros(n, dtype=np.uint8)
    row[(k * k) % n] = 1                                       # s_0j = 1 for j in Q
    idx = (np.arange(n)[:, None] + np.arange(n)[None, :]) % n  # s_ij = s_0,(i+j) mod n
    return row[idx]


def smallest_s_matrix_order(n_leds: int) -> int:
    """Smallest S-matrix order that can drive ``n_leds`` lights.

    Parameters
    ----------
    n_leds : int
        Number of light sources, >= 1.

    Returns
    -------
    n : int
        Smallest prime ``n >= n_leds`` with ``n % 4 == 3`` (199 for 198 LEDs,
        3 for 1-3 LEDs).
    """
    if isinstance(n_leds, bool) or not isinstance(n_leds, (int, np.integer)) or n_leds < 1:
        raise ValueError(f"n_leds must be a positive integer, got {n_leds!r}")
    n = max(int(n_leds), 3)
    while not is_s_matrix_order(n):
        n += 1
    return n


def multiplexing_patterns(n_leds: int) -> np.ndarray:
    """Illumination patterns of a multiplexed capture with ``n_leds`` lights.

    Parameters
    ----------
    n_leds : int
        Number of light sources.

    Returns
    -------
    patterns : (n, n_leds) ndarray of uint8
        The S-matrix of order ``n = smallest_s_matrix_order(n_leds)`` with its
        columns truncated to the first ``n_leds``. The number of rows stays
        ``n`` (one pattern per row of the full S-matrix): with ``n > n_leds``
        the system is over-determined and is solved in the least-squares sense
        (thesis, App. "Multiplexed acquisition" 3.1).

    Notes
    -----
    Every row has at least one light on whenever ``n_leds >= 2`` since a row
    of an S-matrix has :math:`(n+1)/2` ones among :math:`n` columns, of which
    at most :math:`n - n_{leds}` are dropped; for 198 LEDs and ``n = 199`` one
    column is dropped. The truncated matrix keeps full column rank (its
    columns are columns of the invertible S-matrix).
    """
    n = smallest_s_matrix_order(n_leds)
    patterns = np.ascontiguousarray(s_matrix(n)[:, :n_leds])
    empty = np.flatnonzero(patterns.sum(axis=1) == 0)
    if empty.size:  # only possible for very small n_leds relative to n (e.g. 1 LED)
        raise ValueError(
            f"the truncated S-matrix of order {n} for {n_leds} lights has patterns {empty.tolist()} "
            f"with no light on; multiplexing needs at least 2 lights"
        )
    return patterns
