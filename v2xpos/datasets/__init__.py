"""Dataset readers: one module per format, and ``load_dataset`` for descriptors and folders.

See docs/datasets.md for the formats, the time mapping and the conventions.
"""
from v2xpos.datasets.loader import describe, load_dataset, load_multi_imu, read_descriptor

__all__ = ["describe", "load_dataset", "load_multi_imu", "read_descriptor"]
