"""Scene fields (hash grid, vanilla NeRF MLP) and their input encodings."""

from .encodings import DenseGridEncoding, FrequencyEncoding, HashGridEncoding
from .fields import FIELDS, EncodedField, Field, GridField, HashGridField, VanillaNeRFField, make_field

__all__ = [
    "FIELDS", "DenseGridEncoding", "EncodedField", "Field", "FrequencyEncoding", "GridField", "HashGridEncoding",
    "HashGridField", "VanillaNeRFField", "make_field",
]
