"""The project's stores, one module per kind: each is created, opened and validated in one place.

- :mod:`tasks.stores.capture`: the ``btf-capture`` store (docs/capture-store.md), with
  :mod:`~tasks.stores.capture_schema`, :mod:`~tasks.stores.capture_validate` and
  :mod:`~tasks.stores.capture_store`;
- :mod:`tasks.stores.btf`: the ``btf-texture`` store (docs/btf-store.md);
- :mod:`tasks.stores.measurement`: the ``btf-measurement`` store (docs/measurement-store.md);
- :mod:`tasks.stores.common`: what every kind shares (problems, plain-JSON attributes, whole-chunk writes).

Each kind keeps its schema name and version in its own module (``tasks.stores.btf.SCHEMA_NAME``);
the package re-exports the capture store's public names (its schema's as ``CAPTURE_SCHEMA_NAME`` /
``CAPTURE_SCHEMA_VERSION``) and the shared ones; the other kinds are imported from their modules.
"""

from tasks.stores.capture import (
    BAYER_PATTERNS,
    LV_ORDER,
    UNITS,
    CaptureMetadata,
    CaptureStore,
    CaptureStoreError,
    capture_target,
    check_capture_target,
    commit_capture,
    create_capture_store,
    finished_capture,
    open_capture_store,
    reusable_capture,
    validate_capture_store,
)
from tasks.stores.capture import SCHEMA_NAME as CAPTURE_SCHEMA_NAME
from tasks.stores.capture import SCHEMA_VERSION as CAPTURE_SCHEMA_VERSION
from tasks.stores.capture_schema import bracket_steps
from tasks.stores.common import Problem, StoreProblemsError, to_json_attr, write_chunk_aligned

__all__ = [
    "BAYER_PATTERNS",
    "CAPTURE_SCHEMA_NAME",
    "CAPTURE_SCHEMA_VERSION",
    "LV_ORDER",
    "UNITS",
    "CaptureMetadata",
    "CaptureStore",
    "CaptureStoreError",
    "Problem",
    "StoreProblemsError",
    "bracket_steps",
    "capture_target",
    "check_capture_target",
    "commit_capture",
    "create_capture_store",
    "finished_capture",
    "open_capture_store",
    "reusable_capture",
    "to_json_attr",
    "validate_capture_store",
    "write_chunk_aligned",
]
