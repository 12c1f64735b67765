"""v2xpos: open multi-vehicle relative positioning and V2V service."""
__version__ = "0.1.0"
