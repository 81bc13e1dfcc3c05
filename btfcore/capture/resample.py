"""Angular resampling of a BTF to a common light x view sampling.

A dome measures each texel at the light/view pairs its geometry gives; a
turntable dome rotates the lights with the sample, so the light directions
differ from view to view. Rendering, compression and the model database need
one common sampling for every BTF (thesis §1.1.2: "Computing the
weights is much more convenient when for all x the sampled omega_{i,o} are
the same"), for example the UBO2014 151 x 151 set (:func:`ubo2014_directions`).

The thesis interpolates a BTF value from 3 x 3 measured pairs,

.. math:: B(\\omega_i, \\omega_o, x) = \\sum_{i=1}^3 \\sum_{j=1}^3 \\lambda_{ij}\\,
          B(\\omega_i^{(i)}, \\omega_o^{(j)}, x),

with weights from 2D Delaunay triangulations of the sampled directions
(§1.1.2). Here the 2D coordinates are the parabolic map of the
upper hemisphere and :math:`\\lambda_{ij} = \\mu_j \\lambda^{(j)}_i`: the
barycentric weights :math:`\\mu_j` of the target view in the triangulation of
the source views, times the barycentric weights :math:`\\lambda^{(j)}_i` of
the target light in the triangulation of the lights measured *with source
view j*. The weights of all pairs form one sparse matrix ``W``
``(n_lv_dst, n_lv_src)`` with at most 9 non-zeros per row, computed once per
sampling pair, and a chunk of texels is resampled by one sparse product
``B_dst = W @ B_src`` (:func:`resample`).

See ``docs/demultiplex-resample.md``.

References
----------
.. [1] The thesis, §1.1.2 (Appearance models: resampling and the 3 x 3 interpolation).
.. [2] W. Heidrich and H.-P. Seidel, "View-independent environment maps",
   Graphics Hardware 1998 (the parabolic map).
.. [3] M. Weinmann, J. Gall and R. Klein, "Material classification based on
   training data synthesized using a BTF database", ECCV 2014 (UBO2014).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import Delaunay, QhullError, cKDTree

from btfcore.dome import UBO_DOME1_RINGS, ring_directions, spherical_to_cartesian

__all__ = [
    "DIRECTION_TOL",
    "barycentric_weights",
    "lv_outside_hull",
    "lv_product",
    "outside_hull",
    "parabolic_map",
    "resample",
    "resample_weights",
    "ubo2014_directions",
    "unique_directions",
]

#: Two unit directions closer than this (Euclidean, ~radians) are the same direction.
DIRECTION_TOL = 1e-6

#: Largest negative z accepted as "on the horizon" (rounding of rotated directions).
_Z_TOL = 1e-9


# --------------------------------------------------------------------------- directions


def _as_dirs(dirs, name: str) -> np.ndarray:
    """Validate ``(n, 3)`` upper-hemisphere directions; return them normalised (float64)."""
    d = np.asarray(dirs, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] == 0:
        raise ValueError(f"{name} must be a non-empty (n, 3) array of directions, got shape {d.shape}")
    finite = np.isfinite(d).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise ValueError(f"{name}[{i}] = {d[i].tolist()} is not finite")
    norm = np.linalg.norm(d, axis=1)
    if np.any(norm < 1e-12):
        i = int(np.argmax(norm < 1e-12))
        raise ValueError(f"{name}[{i}] is the zero vector, not a direction")
    d = d / norm[:, None]
    below = d[:, 2] < -_Z_TOL
    if below.any():
        i = int(np.argmax(below))
        raise ValueError(
            f"{name}[{i}] = {d[i].tolist()} points below the sample plane (z < 0); "
            f"directions must lie in the upper hemisphere"
        )
    return d


def parabolic_map(dirs: np.ndarray) -> np.ndarray:
    """Parabolic-map coordinates of upper-hemisphere directions.

    Parameters
    ----------
    dirs : (n, 3) array_like
        Directions with ``z >= 0`` (normalised here).

    Returns
    -------
    xy : (n, 2) ndarray of float64
        Points in the unit disc: the zenith maps to the origin, the horizon
        to the unit circle, ``theta`` to radius ``tan(theta / 2)``.

    Raises
    ------
    ValueError
        On a zero, non-finite or downward (``z < 0``) direction; the message
        names its index.

    Notes
    -----
    .. math:: (x, y) = \\frac{(d_x, d_y)}{1 + d_z}

    (Heidrich & Seidel 1998). The map is conformal and distorts solid angle
    by at most a factor 4 over the hemisphere, so a Delaunay triangulation
    in it has well-shaped triangles on the sphere too.
    """
    d = _as_dirs(dirs, "dirs")
    return d[:, :2] / (1.0 + np.maximum(d[:, 2:3], 0.0))          # eq. (x, y) = (dx, dy) / (1 + dz)


def ubo2014_directions() -> np.ndarray:
    """The 151 directions of the UBO2014 BTF database.

    Returns
    -------
    dirs : (151, 3) ndarray of float64
        Unit vectors, ring by ring: ``theta`` = 0, 11, 23.5, 30, 37.5, 45,
        52.5, 60, 67.5, 75 deg with 1, 6, 12, 12, 12, 18, 18, 24, 24, 24
        directions and azimuth offsets 0, 15, 0, 15, 0, 0, 7.5, 0, 7.5, 0 deg
        (the fully parallel dome, :data:`btfcore.dome.UBO_DOME1_RINGS`).
        Used for both the light and the view directions (151 x 151 = 22,801
        pairs; see :func:`lv_product`).
    """
    th, n, off = zip(*UBO_DOME1_RINGS)
    theta, phi = ring_directions(th, n, off)
    return spherical_to_cartesian(theta, phi)


def lv_product(light_dirs: np.ndarray, view_dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """All light/view pairs of a light set and a view set, view-major.

    Parameters
    ----------
    light_dirs : (n_l, 3) array_like
    view_dirs : (n_v, 3) array_like

    Returns
    -------
    light, view : (n_v * n_l, 3) ndarray of float64
        Row ``v * n_l + l`` is the pair (light ``l``, view ``v``): the light
        index runs fastest, as in :meth:`btfcore.dome.Device.lv_directions`.
    """
    L = _as_dirs(light_dirs, "light_dirs")
    V = _as_dirs(view_dirs, "view_dirs")
    n_l, n_v = len(L), len(V)
    light = np.broadcast_to(L[None], (n_v, n_l, 3)).reshape(-1, 3).copy()
    view = np.broadcast_to(V[:, None], (n_v, n_l, 3)).reshape(-1, 3).copy()
    return light, view


def unique_directions(dirs: np.ndarray, tol: float = DIRECTION_TOL) -> tuple[np.ndarray, np.ndarray]:
    """Merge directions closer than ``tol``.

    Parameters
    ----------
    dirs : (n, 3) array_like
        Directions (normalised here).
    tol : float
        Euclidean distance between unit vectors (about radians) under which
        two directions are one; chains of close directions merge too.

    Returns
    -------
    unique : (m, 3) ndarray of float64
        One representative (the first occurrence) per group, in order of
        first occurrence.
    inverse : (n,) ndarray of intp
        ``unique[inverse[i]]`` is the representative of ``dirs[i]``.
    """
    d = _as_dirs(dirs, "dirs")
    n = len(d)
    pairs = cKDTree(d).query_pairs(r=float(tol), output_type="ndarray")
    if len(pairs) == 0:
        return d, np.arange(n)
    graph = sp.coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    _, first = np.unique(labels, return_index=True)               # first member of each label
    order = np.argsort(first)                                     # labels by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    inverse = rank[labels]
    return d[np.sort(first)], inverse


# --------------------------------------------------------------------------- 2D barycentric weights


def _segment_weights(P: np.ndarray, edges: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest point of the segments ``edges`` (pairs of rows of ``P``) to each point of ``Q``.

    Returns the segment's vertex indices ``(m, 2)`` and weights ``(m, 2)``.
    """
    a, b = P[edges[:, 0]], P[edges[:, 1]]                         # (e, 2)
    ab = b - a
    len2 = np.maximum(np.einsum("ej,ej->e", ab, ab), 1e-300)
    aq = Q[:, None, :] - a[None]                                  # (m, e, 2)
    t = np.clip(np.einsum("mej,ej->me", aq, ab) / len2, 0.0, 1.0)  # eq. t = clip((q-a).(b-a) / |b-a|^2)
    dist2 = np.sum((aq - t[..., None] * ab) ** 2, axis=-1)
    best = np.argmin(dist2, axis=1)
    tb = t[np.arange(len(Q)), best]
    return edges[best], np.stack([1.0 - tb, tb], axis=1)


def _weights_2d(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Barycentric weights of points ``Q`` (m, 2) in the Delaunay triangulation of distinct ``P`` (n, 2).

    Returns ``(rows, cols, vals)`` of a sparse (m, n) matrix.
    """
    n, m = len(P), len(Q)
    if n == 1:
        return np.arange(m), np.zeros(m, dtype=np.intp), np.ones(m)
    centred = P - P.mean(axis=0)
    s = np.linalg.svd(centred, compute_uv=False)
    if n == 2 or s[1] <= 1e-9 * max(s[0], 1e-300):
        # collinear directions: piecewise-linear interpolation along the line, clamped at its ends
        axis = np.linalg.svd(centred, full_matrices=False)[2][0]
        order = np.argsort(centred @ axis)
        edges = np.stack([order[:-1], order[1:]], axis=1)
        verts, w = _segment_weights(P, edges, Q)
        return np.repeat(np.arange(m), 2), verts.ravel(), w.ravel()
    try:
        tri = Delaunay(P)
    except QhullError as exc:  # pragma: no cover - qhull failures on distinct, non-collinear points
        raise ValueError(f"Delaunay triangulation of {n} directions failed: {exc}") from exc
    simplex = tri.find_simplex(Q)
    rows = np.empty((m, 3), dtype=np.intp)
    cols = np.zeros((m, 3), dtype=np.intp)
    vals = np.zeros((m, 3))
    rows[:] = np.arange(m)[:, None]
    inside = simplex >= 0
    if inside.any():
        T = tri.transform[simplex[inside]]                        # (k, 3, 2): inverse affine map and origin
        b = np.einsum("kij,kj->ki", T[:, :2], Q[inside] - T[:, 2])
        bary = np.concatenate([b, 1.0 - b.sum(axis=1, keepdims=True)], axis=1)  # eq. barycentric coordinates
        bary[bary < 1e-12] = 0.0                                  # rounding at edges and vertices
        cols[inside] = tri.simplices[simplex[inside]]
        vals[inside] = bary / bary.sum(axis=1, keepdims=True)
    if (~inside).any():
        # outside the convex hull: the nearest point on the hull boundary (an edge or a vertex)
        verts, w = _segment_weights(P, tri.convex_hull, Q[~inside])
        cols[~inside, :2] = verts
        vals[~inside, :2] = w
    return rows.ravel(), cols.ravel(), vals.ravel()


def _split_duplicates(rows, cols, vals, inverse: np.ndarray, shape: tuple[int, int]) -> sp.csr_matrix:
    """Spread each unique direction's weight equally over the source rows that share it."""
    counts = np.bincount(inverse, minlength=int(cols.max(initial=0)) + 1)
    members = np.argsort(inverse, kind="stable")                  # source rows grouped by unique index
    start = np.concatenate([[0], np.cumsum(counts)])
    reps = counts[cols]
    r = np.repeat(rows, reps)
    v = np.repeat(vals / reps, reps)
    offs = np.arange(len(r)) - np.repeat(np.cumsum(reps) - reps, reps)
    c = members[np.repeat(start[cols], reps) + offs]
    W = sp.csr_matrix((v, (r, c)), shape=shape)
    W.eliminate_zeros()
    return W


def barycentric_weights(src_dirs: np.ndarray, dst_dirs: np.ndarray) -> sp.csr_matrix:
    """Interpolation weights from one set of directions to another.

    Parameters
    ----------
    src_dirs : (n_src, 3) array_like
        Sampled directions, upper hemisphere (normalised here).
    dst_dirs : (n_dst, 3) array_like
        Target directions, upper hemisphere.

    Returns
    -------
    W : (n_dst, n_src) scipy.sparse.csr_matrix of float64
        Non-negative, rows sum to 1, at most 3 non-zeros per row (more only
        where source directions repeat). ``f(dst) ~ W @ f(src)``.

    Notes
    -----
    The source directions are triangulated (Delaunay) in parabolic-map
    coordinates :math:`p(d)` (:func:`parabolic_map`), as the thesis does
    with "2D Delaunay triangulation of the corresponding sample points"
    (§1.1.2). A target :math:`q = p(d)` inside triangle
    :math:`(a, b, c)` gets its barycentric coordinates,

    .. math:: q = \\lambda_a a + \\lambda_b b + \\lambda_c c, \\quad
              \\lambda \\ge 0, \\; \\textstyle\\sum \\lambda = 1,

    so any function linear in :math:`p` is reproduced exactly there. A
    target **outside the convex hull** of the sources (e.g. a 75 deg target
    between the 12 azimuths of a turntable dome's lowest camera ring) gets
    the weights of the **nearest point on the hull boundary**: linear
    interpolation along the closest hull edge, or the closest hull vertex.
    This is constant extrapolation along the edge normal, never negative
    weights; :func:`outside_hull` tells which targets were extrapolated.

    Source directions closer than :data:`DIRECTION_TOL` are merged and the
    weight is shared equally between them (their values are averaged).
    Collinear sources (e.g. the cameras of one meridian) are interpolated
    piecewise-linearly along their line.
    """
    src = _as_dirs(src_dirs, "src_dirs")
    dst = _as_dirs(dst_dirs, "dst_dirs")
    uniq, inverse = unique_directions(src)
    rows, cols, vals = _weights_2d(parabolic_map(uniq), parabolic_map(dst))
    return _split_duplicates(rows, cols, vals, inverse, (len(dst), len(src)))


def outside_hull(src_dirs: np.ndarray, dst_dirs: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Which targets lie outside the convex hull of the sources (in the parabolic map).

    Parameters
    ----------
    src_dirs : (n_src, 3) array_like
    dst_dirs : (n_dst, 3) array_like
    tol : float
        Distance in parabolic-map units within which a target counts as inside.

    Returns
    -------
    outside : (n_dst,) ndarray of bool
        True where :func:`barycentric_weights` extrapolates (nearest hull point).
    """
    uniq, _ = unique_directions(src_dirs)
    P, Q = parabolic_map(uniq), parabolic_map(dst_dirs)
    rows, cols, vals = _weights_2d(P, Q)
    W = sp.csr_matrix((vals, (rows, cols)), shape=(len(Q), len(P)))
    return np.linalg.norm(W @ P - Q, axis=1) > tol


# --------------------------------------------------------------------------- 4D light x view weights


def _group(inverse: np.ndarray, n_groups: int) -> list[np.ndarray]:
    order = np.argsort(inverse, kind="stable")
    bounds = np.cumsum(np.bincount(inverse, minlength=n_groups))[:-1]
    return np.split(order, bounds)


def resample_weights(
    src_light: np.ndarray,
    src_view: np.ndarray,
    dst_light: np.ndarray,
    dst_view: np.ndarray,
) -> sp.csr_matrix:
    """Sparse light x view interpolation matrix between two light/view samplings.

    Parameters
    ----------
    src_light, src_view : (n_lv_src, 3) array_like
        Light and view direction of every measured row of the source BTF, in
        the sample frame (e.g. :meth:`Device.lv_directions`). Need not be a
        Cartesian product: on a turntable dome every view has its own
        (rotated) light set.
    dst_light, dst_view : (n_lv_dst, 3) array_like
        Light and view direction of every target row (e.g.
        ``lv_product(ubo2014_directions(), ubo2014_directions())``).

    Returns
    -------
    W : (n_lv_dst, n_lv_src) scipy.sparse.csr_matrix of float64
        Non-negative, rows sum to 1, at most 9 non-zeros per row (3 views x
        3 lights) unless source pairs repeat. ``B_dst = W @ B_src``.

    Notes
    -----
    1. The distinct source views :math:`v_j` (merged within
       :data:`DIRECTION_TOL`, so a zenith camera seen at several turntable
       angles is one view) are triangulated in the parabolic map, giving
       the view weights :math:`\\mu_j(v)` of every target view
       (:func:`barycentric_weights`).
    2. For each source view :math:`v_j` the lights measured with it (the
       union over the turntable positions that share the view) are
       triangulated on their own, giving light weights
       :math:`\\lambda^{(j)}_i(l)`. Per-view light triangulation is what a
       turntable dome needs: its light set rotates with the sample.
    3. The target pair :math:`(l, v)` gets

       .. math:: W_{(l, v), (i, j)} = \\mu_j(v)\\, \\lambda^{(j)}_i(l)

       (thesis §1.1.2, with :math:`\\lambda_{ij}` factorised).

    When the source is a Cartesian product (every view has the same lights),
    step 2 is computed once and ``W`` is, up to the order of rows and
    columns, ``kron(view_weights, light_weights)``. A function of the form
    :math:`a + b^T p(l) + c^T p(v) + p(l)^T D p(v)` is reproduced exactly
    wherever the targets are inside the source hulls.
    """
    sl = _as_dirs(src_light, "src_light")
    sv = _as_dirs(src_view, "src_view")
    dl = _as_dirs(dst_light, "dst_light")
    dv = _as_dirs(dst_view, "dst_view")
    if len(sl) != len(sv):
        raise ValueError(f"src_light has {len(sl)} rows but src_view {len(sv)}: one light and one view per row")
    if len(dl) != len(dv):
        raise ValueError(f"dst_light has {len(dl)} rows but dst_view {len(dv)}: one light and one view per row")
    n_src, n_dst = len(sl), len(dl)

    sv_u, sv_inv = unique_directions(sv)
    dv_u, dv_inv = unique_directions(dv)
    dl_u, dl_inv = unique_directions(dl)
    V = barycentric_weights(sv_u, dv_u).tocsc()                   # (n_dv, n_sv): view weights mu_j
    dst_rows_by_view = _group(dv_inv, len(dv_u))

    rows, cols, vals = [], [], []
    cache: dict[bytes, sp.csr_matrix] = {}
    for j, members in enumerate(_group(sv_inv, len(sv_u))):
        col = slice(V.indptr[j], V.indptr[j + 1])
        views, mu = V.indices[col], V.data[col]
        if len(views) == 0:
            continue                                              # no target view uses source view j
        lights = sl[members]
        key = np.round(lights / DIRECTION_TOL).astype(np.int64).tobytes()
        L = cache.get(key)
        if L is None:
            L = cache[key] = barycentric_weights(lights, dl_u)    # (n_dl, n_members): lambda^(j)
        r = np.concatenate([dst_rows_by_view[v] for v in views])
        scale = np.repeat(mu, [len(dst_rows_by_view[v]) for v in views])
        Lr = L[dl_inv[r]].tocoo()                                 # light weights of each target row
        rows.append(r[Lr.row])
        cols.append(members[Lr.col])
        vals.append(scale[Lr.row] * Lr.data)                      # eq. W = mu_j(v) lambda^(j)_i(l)  (§1.1.2)
    W = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(n_dst, n_src))
    W.sum_duplicates()
    W.eliminate_zeros()
    return W


def lv_outside_hull(
    src_light: np.ndarray,
    src_view: np.ndarray,
    dst_light: np.ndarray,
    dst_view: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Which target light/view pairs :func:`resample_weights` extrapolates.

    Parameters
    ----------
    src_light, src_view : (n_lv_src, 3) array_like
        Light and view direction of every source row (as for :func:`resample_weights`).
    dst_light, dst_view : (n_lv_dst, 3) array_like
        Light and view direction of every target row.

    Returns
    -------
    view_outside : (n_lv_dst,) ndarray of bool
        The target view lies outside the hull of the distinct source views
        (its view weights are those of the nearest hull point).
    light_outside : (n_lv_dst,) ndarray of bool
        For at least one source view :math:`j` with :math:`\\mu_j(v) > 0`,
        the target light lies outside the hull of the lights measured with
        view :math:`j` (its light weights there are those of the nearest hull
        point).

    Notes
    -----
    A row with neither flag is a true barycentric interpolation: functions
    of the form :math:`a + b^T p(l) + c^T p(v) + p(l)^T D p(v)` are
    reproduced exactly there. The source views and their light sets are
    grouped exactly as in :func:`resample_weights`.
    """
    sl = _as_dirs(src_light, "src_light")
    sv = _as_dirs(src_view, "src_view")
    dl = _as_dirs(dst_light, "dst_light")
    dv = _as_dirs(dst_view, "dst_view")
    if len(sl) != len(sv) or len(dl) != len(dv):
        raise ValueError(f"src_light/src_view have {len(sl)}/{len(sv)} rows and dst_light/dst_view "
                         f"{len(dl)}/{len(dv)}: one light and one view per row")
    sv_u, sv_inv = unique_directions(sv)
    dv_u, dv_inv = unique_directions(dv)
    dl_u, dl_inv = unique_directions(dl)
    view_out = outside_hull(sv_u, dv_u)[dv_inv]
    V = barycentric_weights(sv_u, dv_u).tocoo()                   # (n_dv, n_sv): which source views each uses
    light_out_u = np.zeros((len(sv_u), len(dl_u)), dtype=bool)    # (n_sv, n_dl)
    cache: dict[bytes, np.ndarray] = {}
    for j in np.unique(V.col):
        lights = sl[sv_inv == j]
        key = np.round(lights / DIRECTION_TOL).astype(np.int64).tobytes()
        if key not in cache:
            cache[key] = outside_hull(lights, dl_u)
        light_out_u[j] = cache[key]
    # a target (light, view) is extrapolated in light if any source view it draws on extrapolates
    used = sp.csr_matrix((np.ones(V.nnz), (V.row, V.col)), shape=V.shape)       # (n_dv, n_sv)
    light_out_dv = (used @ light_out_u.astype(np.float64)) > 0                   # (n_dv, n_dl)
    return view_out, light_out_dv[dv_inv, dl_inv]


def resample(B: np.ndarray, W) -> np.ndarray:
    """Apply resampling weights to a BTF (or a chunk of its texels).

    Parameters
    ----------
    B : (n_lv_src, n_tx) or (n_lv_src, ...) ndarray of float
        Source BTF: rows light/view pairs, columns texels x channels.
    W : (n_lv_dst, n_lv_src) sparse matrix or ndarray
        From :func:`resample_weights` (or :func:`barycentric_weights`).

    Returns
    -------
    B_dst : (n_lv_dst, ...) ndarray
        ``W @ B``, float32 for float32 input and float64 otherwise.

    Raises
    ------
    ValueError
        On mismatched shapes or NaN/Inf in ``B`` (names the index).
    """
    x = np.asarray(B)
    if not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)):
        raise ValueError(f"B must be real numbers, got dtype {x.dtype}")
    if W.ndim != 2 or x.ndim < 1 or W.shape[1] != x.shape[0]:
        raise ValueError(f"W has shape {W.shape} but B has {x.shape}: W must be (n_lv_dst, {x.shape[0]})")
    finite = np.isfinite(x)
    if not finite.all():
        idx = tuple(int(v) for v in np.unravel_index(int(np.argmin(finite)), x.shape))
        raise ValueError(f"B contains NaN or Inf: B{list(idx)} = {float(x[idx])!r}")
    dtype = np.float32 if x.dtype == np.float32 else np.float64
    Wd = W.astype(dtype)
    out = Wd @ x.reshape(x.shape[0], -1).astype(dtype, copy=False)   # eq. B_dst = W B_src
    return np.asarray(out).reshape((W.shape[0],) + x.shape[1:])
