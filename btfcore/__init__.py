"""Pure numerics of btf-pipeline: arrays in, arrays out.

No file paths, no dask, no prefect, no zarr: those live in :mod:`tasks` and
:mod:`flows` (docs/architecture.md, "Layers"). A test enforces the import direction.
"""

__version__ = "0.1.0"


class BtfWarning(UserWarning):
    """Warning raised by btf-pipeline's own code (tests turn it into an error)."""
