"""The rig's global colour mixing, as the user measured it: ``--mixing FILE``.

When one 3x3 camera matrix C (camera channel by light primary) and one projector matrix
P (light primary by projector primary) hold for the whole rig (Chen et al., PROCAMS
2008), a colour T is ``T[3 p + i, 3 q + j] = sum_k C[i, k] T_k[p, q] P[k, j]``, three grey
transports between two 3x3 mixings, and the engine can take its cheaper global path.
Estimating C and P from the captures is not done here; a build given them records them
in T's metadata under :data:`MIXING_KEY` as ``{"camera": C, "projector": P}`` (nested
lists, rows first), the key the engine reads.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import AcquisitionError

MIXING_KEY = "mixing"
#: A mixing whose condition number exceeds this cannot be undone in float32.
MAX_CONDITION = 1e6
ROLES = ("camera", "projector")


@dataclass(frozen=True)
class Mixing:
    """The rig's global colour mixing.

    Attributes
    ----------
    camera : ndarray, shape (3, 3), C: camera channel i's response to light primary k
    projector : ndarray, shape (3, 3), P: light primary k from projector primary j
    """

    camera: np.ndarray
    projector: np.ndarray

    def to_metadata(self) -> dict:
        """``{"camera": [[...] x 3], "projector": [[...] x 3]}``, JSON-serialisable."""
        return {role: getattr(self, role).tolist() for role in ROLES}

    def describe(self) -> str:
        """One line: both matrices, rows separated by ``;``."""
        def text(m):
            return "; ".join(" ".join(f"{v:.4g}" for v in row) for row in m)
        return f"camera [{text(self.camera)}], projector [{text(self.projector)}]"


def read_mixing(path) -> Mixing:
    """The mixing of a JSON file ``{"camera": 3x3, "projector": 3x3}``.

    Raises
    ------
    AcquisitionError
        (naming the file) no such file, not JSON, a matrix missing, not 3x3 of finite
        numbers, or singular or ill-conditioned (condition number above
        :data:`MAX_CONDITION`).
    """
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise AcquisitionError("no such mixing file", path) from None
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise AcquisitionError(f"the mixing file is not JSON ({exc.__class__.__name__})",
                               path) from None
    if not isinstance(d, dict):
        raise AcquisitionError('the mixing file must hold {"camera": 3x3, "projector": 3x3}',
                               path)
    return Mixing(*(_matrix(d, role, path) for role in ROLES))


def _matrix(d: dict, role: str, path: Path) -> np.ndarray:
    if role not in d:
        raise AcquisitionError(f'the mixing file has no "{role}" matrix (3x3)', path)
    try:
        m = np.array(d[role], dtype=np.float64)
    except (TypeError, ValueError):
        m = None
    if m is None or m.shape != (3, 3) or not np.isfinite(m).all():
        raise AcquisitionError(f'the "{role}" mixing is not a 3x3 matrix of finite numbers',
                               path)
    condition = np.linalg.cond(m)
    if not condition <= MAX_CONDITION:
        raise AcquisitionError(f'the "{role}" mixing is singular or ill-conditioned '
                               f"(condition number {condition:.3g}): it cannot be undone",
                               path)
    return m
