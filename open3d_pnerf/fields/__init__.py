"""Scene fields (hash grid, dense grid, vanilla NeRF MLP) and their input encodings. Which one a
reconstruction uses, and with what settings, is chosen by its config (config.FIELD_CONFIGS)."""

from .encodings import DenseGridEncoding, FrequencyEncoding, HashGridEncoding
from .fields import EncodedField, Field, GridField, HashGridField, VanillaNeRFField

__all__ = [
    "DenseGridEncoding", "EncodedField", "Field", "FrequencyEncoding", "GridField", "HashGridEncoding",
    "HashGridField", "VanillaNeRFField",
]
