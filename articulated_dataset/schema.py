"""Old home of the shard schema: it lives in :mod:`articulated_dataset.format.schema` now
(re-exported here so that existing imports keep working)."""

from .format.schema import (  # noqa: F401
    FIELDS,
    FIELDS_BY_NAME,
    IMAGE_FIELDS,
    K_DATASET,
    LABEL_FIELDS,
    MASK_BACKGROUND,
    MASK_BODY,
    MASK_FIRST_PART,
    R_DATASET,
    ROOT_ATTRS,
    Field,
    check_version,
    markdown_table,
    resolve_shape,
    validate_arrays,
)

if __name__ == "__main__":  # pragma: no cover - doc helper
    print(markdown_table())
