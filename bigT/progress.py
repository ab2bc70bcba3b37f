"""Progress bars, one policy for all of bigT.

A bar is drawn only when it is asked for (``progress`` True, or None for "when it can")
and stderr is a terminal: tqdm's ``disable=None``. Logs and pipes get no carriage
returns; the summaries printed at the end are what they keep.
"""

from __future__ import annotations

import sys


class _NoBar:
    """What :func:`progress_bar` returns when nothing would be drawn: it iterates, is a
    context manager and takes ``update``, as a disabled tqdm bar does, without
    importing tqdm (``tqdm.auto`` probes for notebooks, ~0.1 s a process)."""

    def __init__(self, iterable=None):
        self._iterable = iterable

    def __iter__(self):
        return iter(() if self._iterable is None else self._iterable)

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> bool:
        return False

    def update(self, n: int = 1) -> None:
        pass

    def close(self) -> None:
        pass


def _would_draw(progress: bool | None) -> bool:
    """tqdm's ``disable=None`` rule: draw when asked and stderr is a terminal."""
    if progress is False:
        return False
    try:
        return sys.stderr is not None and sys.stderr.isatty()
    except (AttributeError, ValueError):  # a replaced or closed stderr
        return False


def progress_bar(iterable=None, *, progress: bool | None = None, **kwargs):
    """``tqdm.auto.tqdm(iterable, **kwargs)``, off when ``progress`` is False or stderr
    is not a terminal (then a stand-in that iterates and takes ``update``). Bars are
    left on screen only when the caller says ``leave``."""
    if not _would_draw(progress):
        return _NoBar(iterable)
    from tqdm.auto import tqdm  # tqdm.auto probes for notebooks (~0.1 s): only when drawn

    kwargs.setdefault("leave", False)
    return tqdm(iterable, disable=None, **kwargs)
