"""The tile cache: decoded tiles and tile rows kept in memory up to a byte budget,
shared by every pass of the engine and by compensation in one process (each worker
process of a cluster has its own)."""

from __future__ import annotations

import threading

import scipy.sparse as sp


def nbytes(value) -> int:
    """Bytes held by a cached value (CSR arrays, or an ndarray)."""
    if sp.issparse(value):
        return int(value.data.nbytes + value.indices.nbytes + value.indptr.nbytes)
    return int(getattr(value, "nbytes", 64))


class TileCache:
    """Values kept in memory, bounded in bytes, thread safe; keys are tuples whose
    first element is the path of the store they come from.

    Entries are admitted while they fit and kept until dropped: the passes of a run
    scan tile rows in the same order every time, and a least-recently-used policy
    smaller than the scan would evict every row just before it is needed again (no
    hit at all); keeping the first rows that fit gives hits on that share of every
    scan. ``budget`` 0 disables caching.
    """

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.used = 0
        self._d: dict = {}
        self._lock = threading.Lock()
        self.hits = self.misses = 0

    def get(self, key, compute):
        """The value under ``key``; computed by ``compute()`` and admitted if it fits
        when absent."""
        with self._lock:
            if key in self._d:
                self.hits += 1
                return self._d[key]
            self.misses += 1
        value = compute()
        size = nbytes(value)
        with self._lock:
            if key not in self._d and self.used + size <= self.budget:
                self._d[key] = value
                self.used += size
        return value

    def admit(self, key, value) -> bool:
        """Keep ``value`` under ``key`` if it fits (an entry already there stays);
        whether it is held now."""
        size = nbytes(value)
        with self._lock:
            if key in self._d:
                return True
            if self.used + size > self.budget:
                return False
            self._d[key] = value
            self.used += size
            return True

    def pop(self, key):
        """The entry under ``key``, no longer held (None when absent): a value that is
        used once, then replaced by what is made from it."""
        with self._lock:
            value = self._d.pop(key, None)
            if value is not None:
                self.used -= nbytes(value)
                self.hits += 1
            return value

    def discard(self, key) -> None:
        """Let go of the entry under ``key``, if held (not counted as a hit)."""
        with self._lock:
            value = self._d.pop(key, None)
            if value is not None:
                self.used -= nbytes(value)

    def lookup(self, key):
        """The entry under ``key``, or None (nothing is computed or admitted)."""
        with self._lock:
            value = self._d.get(key)
            if value is not None:
                self.hits += 1
            return value

    def has_room(self, size: int) -> bool:
        """Whether an entry of ``size`` bytes would be admitted now."""
        with self._lock:
            return self.used + int(size) <= self.budget

    def resize(self, budget: int) -> None:
        """Set the budget; entries admitted last are forgotten until it holds."""
        with self._lock:
            self.budget = int(budget)
            while self.used > self.budget and self._d:
                self.used -= nbytes(self._d.pop(next(reversed(self._d))))

    def drop(self, prefix) -> None:
        """Forget every entry of the store at path ``prefix``."""
        self.drop_where(lambda path: path == str(prefix))

    def drop_where(self, predicate) -> None:
        """Forget every entry whose key's first element (a store path) satisfies
        ``predicate``."""
        with self._lock:
            for k in [k for k in self._d if predicate(k[0])]:
                self.used -= nbytes(self._d.pop(k))
