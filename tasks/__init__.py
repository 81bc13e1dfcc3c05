"""I/O over chunks: Zarr stores, Dask tasks.

Importing any ``tasks`` module installs :class:`tasks.integrity.LocatingCodecPipeline`, so that in
every process (Dask workers included) a chunk that fails its checksum is named (store, array, chunk).
"""

from tasks import integrity as _integrity  # noqa: F401  (installs the locating codec pipeline)
