"""What the engine records in the inverse store, typed: one :class:`TermRecord` per term
and the :class:`SeriesRecord` of the whole series.

Storage keeps a generic record (:class:`bigT.storage.InverseRecord`: the term held, its
directory, the tile size, one :class:`bigT.storage.TermEntry` per term) and an opaque
``details`` mapping beside it; these classes fill that mapping and read it back. The
JSON keys are those of docs/FORMAT.md ("The inverse store"), unchanged since before the
split, so stores written earlier open and resume.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, Mapping

from ..schedule.costs import TaskCosts
from ..storage.inverse_store import InverseRecord, TermEntry, as_count, damaged_record


@dataclass(frozen=True)
class TermRecord:
    """One row of the report: the state after term ``term``.

    ``seconds`` is the term's wall time, its residual estimate's ``residual_seconds``
    included; ``multiply_adds`` counts its sparse products' multiply-adds and
    ``kernel_seconds`` the time its tasks spent inside the product kernel (summed over
    tasks: thread-seconds). Records written before these were counted read 0.
    ``engine_path`` is the path that computed it, ``"in-memory"`` or ``"out-of-core"``
    (:mod:`.engine_path`; stored only for the former: records without it read the
    latter). ``tasks`` is what the term's tasks cost, one
    :class:`~bigT.schedule.costs.TaskCosts` per kind (its passes and its residual
    estimate's mat-vecs; empty for a term computed in memory, and in records written
    before they were kept).
    """

    term: int
    seconds: float
    nnz_P: int
    nnz_X: int
    tiles_computed: int
    tiles_skipped: int
    rows_skipped: int
    residual: float | None
    residual_abs: float | None
    multiply_adds: int = 0
    kernel_seconds: float = 0.0
    residual_seconds: float = 0.0
    engine_path: str = "out-of-core"
    tasks: tuple[TaskCosts, ...] = ()

    @classmethod
    def from_dict(cls, d: Mapping) -> "TermRecord":
        """Raises TypeError/ValueError on fields of the wrong type or sign (a damaged
        record: :meth:`SeriesRecord.from_stored` names the store)."""
        values = {}
        for f in dataclasses.fields(cls):
            v = d.get(f.name, None if f.default is dataclasses.MISSING else f.default)
            if f.name == "tasks":
                values[f.name] = tuple(TaskCosts.from_dict(t) for t in v or ())
            elif f.name in ("residual", "residual_abs"):
                values[f.name] = None if v is None else float(v)
            elif f.type in ("float", float):  # a string under future annotations
                values[f.name] = float(v or 0.0)
            elif f.type in ("str", str):
                values[f.name] = str(v)
            else:
                values[f.name] = as_count(v, f.name)
        return cls(**values)

    def to_dict(self) -> dict:
        """The stored keys; ``engine_path`` only for a term computed in memory, so that
        an out-of-core run writes the keys it wrote before the in-memory path existed
        (an absent key reads as out of core); ``tasks`` only when the term's tasks
        were measured."""
        d = dataclasses.asdict(self)
        if d["engine_path"] == "out-of-core":
            del d["engine_path"]
        if d["tasks"]:
            d["tasks"] = [t.to_dict() for t in self.tasks]
        else:
            del d["tasks"]
        return d

    def to_entry(self) -> TermEntry:
        """The store's entry: ``term``, and the rest as its details."""
        details = self.to_dict()
        return TermEntry(details.pop("term"), details)

    @classmethod
    def from_entry(cls, entry: TermEntry) -> "TermRecord":
        return cls.from_dict({**entry.details, "term": entry.term})


@dataclass(frozen=True)
class SeriesRecord:
    """The engine's record of the series held in an inverse store.

    Attributes
    ----------
    params : mapping
        What the inverse depends on (:func:`bigT.algorithms.fingerprint.inverse_fingerprint`).
    term : int or None
        T_term^-1 is held (None before term 0 is complete).
    dir : int or None
        Term directory the redirect points at (``term`` may be beyond it once the
        series is exhausted: every later term equals it).
    history : tuple of TermRecord
    tile_size : int or None
        Tile size of the term stores (T's, or a divisor of it for more tasks).
    spectral_radius : float or None
        The estimate of rho(M) made before term 0 (:mod:`bigT.spectral`).
    spectral_uncertainty : float or None
        rho is within ``spectral_radius`` +- this (a bracket's half-width, or a Ritz
        residual).
    spectral_products : int or None
        Products with M the estimate took.
    spectral_method : str or None
        How it was estimated (:attr:`bigT.spectral.SpectralRadius.method`); None in
        stores written before it was recorded.
    exhausted_at : int or None
        The term after which every term is zero.
    excluded_pixels : int or None
    """

    params: Mapping[str, Any]
    term: int | None = None
    dir: int | None = None
    history: tuple[TermRecord, ...] = ()
    tile_size: int | None = None
    spectral_radius: float | None = None
    spectral_uncertainty: float | None = None
    spectral_products: int | None = None
    spectral_method: str | None = None
    exhausted_at: int | None = None
    excluded_pixels: int | None = None

    @property
    def residual(self) -> float | None:
        """The relative residual estimate of the last term computed."""
        return self.history[-1].residual if self.history else None

    def replace(self, **changes) -> "SeriesRecord":
        return dataclasses.replace(self, **changes)

    def to_stored(self) -> InverseRecord:
        """The storage layer's record, the details under their FORMAT.md keys."""
        details = {name: getattr(self, name) for name in _DETAILS}
        details["residual"] = self.residual
        if self.spectral_method is None:  # written only once known (older stores lack it)
            del details["spectral_method"]
        return InverseRecord(self.params, self.term, self.dir,
                             tuple(h.to_entry() for h in self.history), self.tile_size,
                             details)

    @classmethod
    def from_stored(cls, record: InverseRecord, path) -> "SeriesRecord":
        """Raises StoreError (naming ``path``) when a detail is damaged."""
        d = record.details
        try:
            history = tuple(TermRecord.from_entry(h) for h in record.history)
            return cls(record.params, record.term, record.dir, history, record.tile_size,
                       _opt(float, d.get("spectral_radius")),
                       _opt(float, d.get("spectral_uncertainty")),
                       _opt(lambda v: as_count(v, "spectral_products"),
                            d.get("spectral_products")),
                       _opt(str, d.get("spectral_method")),
                       _opt(lambda v: as_count(v, "exhausted_at"), d.get("exhausted_at")),
                       _opt(lambda v: as_count(v, "excluded_pixels"), d.get("excluded_pixels")))
        except (TypeError, ValueError, AttributeError) as exc:
            raise damaged_record(exc, path) from None


#: The fields kept in the stored record's details (the residual is derived).
_DETAILS = ("spectral_radius", "exhausted_at", "excluded_pixels", "spectral_uncertainty",
            "spectral_products", "spectral_method")


def _opt(convert, value):
    return None if value is None else convert(value)
