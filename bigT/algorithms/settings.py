"""The settings of one :func:`~bigT.algorithms.stratified_inverse` run, checked once and
frozen: the pruning thresholds (:class:`Thresholds`) and the rest of the series
(:class:`SeriesSettings`).

The user-facing names of the thresholds are ``prune``, ``prune_feed`` and
``prune_operator`` (``stratified_inverse``, ``bigT invert``, the store's fingerprint and
metadata); the tasks read them from :class:`bigT.schedule.spec.PassSpec` as
``threshold``, ``feed_threshold`` and ``operator_threshold``. :meth:`Thresholds.spec_fields`
is the one place that maps the first names to the second.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..errors import UNSET, BigTError
from .methods import METHODS, SeriesMethod
from .records import SeriesRecord


@dataclass(frozen=True)
class Thresholds:
    """Where the series' products drop small entries (all dimensionless).

    Attributes
    ----------
    prune : float >= 0
        Entries of each new term below it are dropped inside the product.
    feed : float >= prune or None
        The power form's threshold on P_k, the next product's factor (None: ``prune``).
    operator : float >= prune or None
        The power form's threshold on M's entries in the products M P_{k-1}, k >= 2
        (None: M whole).
    """

    prune: float
    feed: float | None = None
    operator: float | None = None

    def spec_fields(self) -> dict:
        """The thresholds under :class:`~bigT.schedule.spec.PassSpec`'s names."""
        return {"threshold": self.prune, "feed_threshold": self.feed,
                "operator_threshold": self.operator}

    def recorded(self) -> dict:
        """The thresholds under their user-facing names, the optional ones only when
        set (so that stores made before they existed resume): the fingerprint's and
        the term metadata's entries."""
        optional = (("prune_feed", self.feed), ("prune_operator", self.operator))
        return {"prune": self.prune,
                **{name: value for name, value in optional if value is not None}}

    def scaled(self, factor: float) -> "Thresholds":
        """Every threshold set times ``factor`` (rounded to 3 digits: ``1e-06``, not
        ``1.0000000000000002e-06``, which the fingerprint would record)."""
        def times(value):
            return None if value is None else float(f"{value * factor:.3g}")
        return Thresholds(times(self.prune), times(self.feed), times(self.operator))

    def describe(self) -> str:
        """``prune 1e-06, P_k pruned at 0.0001, M pruned at 0.001 in the products``."""
        text = f"prune {self.prune:g}"
        if self.feed is not None:
            text += f", P_k pruned at {self.feed:g}"
        if self.operator is not None:
            text += f", M pruned at {self.operator:g} in the products"
        return text


@dataclass(frozen=True)
class SeriesSettings:
    """What one run computes and when it stops (:func:`stratified_inverse`'s
    arguments of the same names)."""

    terms: int
    thresholds: Thresholds
    tol: float | None
    progress: bool
    force: bool
    seed: int
    overwrite: bool = False
    on_term: Callable[[SeriesRecord], str | None] | None = None


def checked_thresholds(method: str, prune, prune_feed=None, prune_operator=None) -> Thresholds:
    """The thresholds of ``method``, checked; a feed threshold equal to ``prune`` is the
    plain power form (None), so that it resumes the same stores.

    Raises
    ------
    BigTError
        A negative threshold, a feed or operator threshold below ``prune``, or one
        given to a method other than the power form.
    """
    if not prune >= 0:
        raise BigTError(f"{{option}} must be >= 0, got {prune!r}", option=("prune", UNSET))
    feed = None if prune_feed is None else float(prune_feed)
    operator = None if prune_operator is None else float(prune_operator)
    for name, value, what in (("prune_feed", feed, "P_k"),
                              ("prune_operator", operator, "products M P_{k-1}")):
        if value is None:
            continue
        if method != "power":
            # Horner's S_{n-1} holds I: M pruned there would miss D_o itself
            raise BigTError(f"{{option}} is a threshold of the power form's {what}; the "
                            f"{method} method has none", option=(name, UNSET))
        if not value >= prune:
            raise BigTError(f"{{option}} must be >= prune ({prune:g}), got {value!r}",
                            option=(name, UNSET))
    return Thresholds(float(prune), None if feed == prune else feed, operator)


def checked_method(method: str, terms, tol) -> SeriesMethod:
    """The series method named ``method``, after checking ``terms`` and ``tol``."""
    if method not in METHODS:
        raise BigTError(f"{{option}} must be one of {', '.join(METHODS)}, got {method!r}",
                        option=("method", UNSET))
    if isinstance(terms, bool) or int(terms) != terms or terms < 0:
        raise BigTError(f"{{option}} must be an integer >= 0, got {terms!r}",
                        option=("terms", UNSET))
    if tol is not None and not tol >= 0:
        raise BigTError(f"{{option}} must be >= 0, got {tol!r}", option=("tol", UNSET))
    return METHODS[method]
