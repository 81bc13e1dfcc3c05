"""Pure numerics of btf-pipeline: arrays in, arrays out.

No file paths, no dask, no prefect, no zarr: those live in :mod:`tasks` and
:mod:`flows` (docs/architecture.md, "Layers"). A test enforces the import direction.
"""

__version__ = "0.1.0"


class BtfWarning(UserWarning):
    """Warning raised by btf-pipeline's own code (tests turn it into an error)."""


class IllConditionedWarning(BtfWarning):
    """A linear solve whose operator is ill-conditioned: noise in its data is amplified up to the condition
    number times (docs/demultiplex-resample.md, "Ill-conditioned solves")."""


#: Condition number above which a solve warns with :class:`IllConditionedWarning`: the float32 rounding of
#: the stored data alone (eps 6e-8) can then grow to 6 % of the result, whatever the noise, and it is the
#: acquisition evaluation's ``ill-conditioned`` flag (``btfcore.acquisition.band_evaluation.ILL_CONDITIONED``)
#: (docs/demultiplex-resample.md, "Ill-conditioned solves").
ILL_CONDITIONED_SOLVE: float = 1e6


def warn_ill_conditioned(condition: float, what: str, fix: str, *, stacklevel: int = 3) -> bool:
    """Warn when a solve's condition number exceeds :data:`ILL_CONDITIONED_SOLVE`.

    Parameters
    ----------
    condition : float
        Condition number of the operator solved (ratio of its extreme singular values); inf or NaN warn.
    what : str
        The operator, e.g. ``"patterns (demultiplexing)"``.
    fix : str
        What to do about it.
    stacklevel : int
        Passed to :func:`warnings.warn` (3: the caller of the function that solves).

    Returns
    -------
    warned : bool
    """
    import warnings

    c = float(condition)
    if c <= ILL_CONDITIONED_SOLVE:                       # NaN compares False: warns
        return False
    warnings.warn(f"ill-conditioned solve: the condition number of {what} is {c:.3g} > {ILL_CONDITIONED_SOLVE:.0e}, "
                  f"so noise in the data can grow up to {c:.3g} times in the result; {fix}",
                  IllConditionedWarning, stacklevel=stacklevel)
    return True
