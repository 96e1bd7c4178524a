"""The array type of the arrays that cross layers, for annotations.

`BatchArray`: numpy where the data layer builds an array (a `SceneBatch`'s), a jax array where
jitted code traces it. The data layer names it without importing jax: this module imports
neither jax nor numpy (both only for the type checker).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Union

if TYPE_CHECKING:
    import jax
    import numpy

# The names in full: the documentation (pdoc) resolves them where they are used.
BatchArray = Union["numpy.ndarray", "jax.Array"]
