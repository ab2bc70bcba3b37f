"""bigT: out-of-core stratified inversion of huge light-transport matrices.

The public API is re-exported here lazily, so ``import bigT`` stays fast and a layer
that is broken does not stop the others from importing.
"""

from __future__ import annotations

import importlib

from .errors import (  # noqa: F401  (re-exported)
    AcquisitionError,
    BigTError,
    CorruptStoreError,
    DiskFullError,
    DivergenceError,
    ImageError,
    IncompleteStoreError,
    InvalidMatrixError,
    MemoryLimitError,
    MemoryLimitWarning,
    NotSquareError,
    ShapeMismatchError,
    StoreError,
)

__version__ = "0.1.0"

# public name -> module that defines it
_LAZY = {
    "BlockCSR": "bigT.storage",
    "BlockCSRWriter": "bigT.storage",
    "open": "bigT.storage",
    "from_scipy": "bigT.storage",
    "scenes": "bigT.scenes",
    "acquisition": "bigT.acquisition",
    "stratified_inverse": "bigT.algorithms",
    "InverseReport": "bigT.algorithms",
    "recover_first_bounce": "bigT.algorithms",
    "compensate": "bigT.compensation",
    "relight": "bigT.compensation",
    "separate_bounces": "bigT.compensation",
    "simulate": "bigT.compensation",
    "Simulation": "bigT.compensation",
    "SimulationReport": "bigT.compensation",
}


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'bigT' has no attribute {name!r}")
    value = importlib.import_module(module)
    return value if name in ("scenes", "acquisition") else getattr(value, name)


def __dir__():
    return sorted(list(globals()) + list(_LAZY))
