"""The project's stores, one module per kind: each is created, opened and validated in one place.

- :mod:`tasks.stores.capture`: the ``btf-capture`` store (docs/capture-store.md).
"""

from tasks.stores.capture import (
    BAYER_PATTERNS,
    LV_ORDER,
    SCHEMA_NAME,
    SCHEMA_VERSION,
    UNITS,
    CaptureMetadata,
    CaptureStore,
    CaptureStoreError,
    Problem,
    bracket_steps,
    check_capture_target,
    create_capture_store,
    open_capture_store,
    to_json_attr,
    validate_capture_store,
    write_chunk_aligned,
)

__all__ = [
    "BAYER_PATTERNS",
    "LV_ORDER",
    "SCHEMA_NAME",
    "SCHEMA_VERSION",
    "UNITS",
    "CaptureMetadata",
    "CaptureStore",
    "CaptureStoreError",
    "Problem",
    "bracket_steps",
    "check_capture_target",
    "create_capture_store",
    "open_capture_store",
    "to_json_attr",
    "validate_capture_store",
    "write_chunk_aligned",
]
