"""Progress bars, one policy for all of bigT.

A bar is drawn only when it is asked for (``progress`` True, or None for "when it can")
and stderr is a terminal: tqdm's ``disable=None``. Logs and pipes get no carriage
returns; the summaries printed at the end are what they keep.
"""

from __future__ import annotations


def progress_bar(iterable=None, *, progress: bool | None = None, **kwargs):
    """``tqdm.auto.tqdm(iterable, **kwargs)``, off when ``progress`` is False or stderr
    is not a terminal. Bars are left on screen only when the caller says ``leave``."""
    from tqdm.auto import tqdm  # tqdm.auto probes for notebooks (~0.1 s): only when drawn

    kwargs.setdefault("leave", False)
    return tqdm(iterable, disable=True if progress is False else None, **kwargs)
