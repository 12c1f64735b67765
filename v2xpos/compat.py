"""Compatibility imports for the oldest supported Python (3.10).

``tomllib`` joined the standard library in Python 3.11 (PEP 680); on 3.10 the same parser is the
``tomli`` package (a dependency for ``python_version < "3.11"`` in pyproject.toml). Every module
that reads TOML imports it from here: ``from v2xpos.compat import tomllib``.
"""
from __future__ import annotations

import sys

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10
    import tomli as tomllib

__all__ = ["tomllib"]
