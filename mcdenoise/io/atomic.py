"""Atomic output: write under a temporary sibling name, then rename over the final name.

The implementation lives in :mod:`mcdenoise.io.safety` (with locks, space checks and one-line OS
errors); these names are kept here for every existing import.
"""

from __future__ import annotations

from mcdenoise.io.safety import _remove_tree, atomic_dir, atomic_file, temp_sibling

__all__ = ["atomic_file", "atomic_dir", "temp_sibling", "_remove_tree"]
