"""Scene fields (hash grid, dense grid, vanilla NeRF MLP), their input encodings and their settings;
a grid field's geometry may be a signed distance (sdf); a forward-facing capture's field sees NDC (ndc).
Which one a reconstruction uses, and with what settings, is chosen by its config (FIELD_CONFIGS)."""

from .encodings import BlockEncoding, DenseGridEncoding, FrequencyEncoding, HashGridEncoding
from .fields import (
    FIELD_CONFIGS,
    EncodedField,
    Field,
    GridConfig,
    GridField,
    HashGridConfig,
    HashGridField,
    VanillaConfig,
    VanillaNeRFField,
    block_boxes,
    block_table_size,
    block_tables,
    grow,
)
from .ndc import NDCWarp
from .proposal import ProposalField
from .sdf import SDFConfig

__all__ = [
    "BlockEncoding", "DenseGridEncoding", "EncodedField", "FIELD_CONFIGS", "Field", "FrequencyEncoding", "GridConfig", "GridField",
    "HashGridConfig", "HashGridEncoding", "HashGridField", "NDCWarp", "ProposalField", "SDFConfig", "VanillaConfig", "VanillaNeRFField",
    "block_boxes", "block_table_size", "block_tables", "grow",
]
