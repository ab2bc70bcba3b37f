"""Rewriting a store in this bigT's format: :func:`upgrade_store` (``bigT convert
OLD.zarr -o NEW.zarr``), for stores written in format 1 (a group per tile), which this
bigT reads but does not add rows to."""

from __future__ import annotations


from ..atomic import refuse_overwriting_inputs
from ..progress import progress_bar
from .objects import as_location
from .block_csr import BlockCSR
from .block_csr import open as open_store
from .replace import check_replaceable, write_root_attrs
from .writer import BlockCSRWriter, built_aside


def upgrade_store(source, path, *, overwrite: bool = False,
                  progress: bool | None = False) -> BlockCSR:
    """Copy the store ``source`` (any format this bigT reads; a versioned store's
    current term) into a new store at ``path`` in this bigT's format, a tile row at a
    time: same shape, tile size, dtype, pixel order, mixing and metadata, entries
    equal. Built aside and moved into place, so a failed call leaves ``path`` as it was.

    Parameters
    ----------
    source : str, os.PathLike or URL
    path : str, os.PathLike or URL (object storage: built in place, see ``built_aside``)
    overwrite : bool
        Replace an existing bigT store at ``path``.
    progress : bool or None
        A bar per tile row (None: when stderr is a terminal).

    Returns
    -------
    BlockCSR, the new store
    """
    old = open_store(source)
    path = as_location(path)
    refuse_overwriting_inputs([path], [source, old.path, old.redirected_from])
    check_replaceable(path, overwrite)
    path.parent.mkdir(parents=True, exist_ok=True)
    with built_aside(path) as tmp:
        writer = BlockCSRWriter(tmp, old.shape, tile_size=old.tile_size, dtype=old.dtype,
                                pixel_order=old.pixel_order, metadata=old.metadata)
        for i in progress_bar(range(old.grid[0]), progress=progress, desc="upgrade",
                              unit="tile row"):
            writer.write_tile_row(i, old.get_tile_row(i))
        if old.mixing is not None:  # the factors travel with the tiles they factor
            write_root_attrs(tmp, writer.attrs.replace(mixing=old.mixing))
        writer.finalize()
    return open_store(path)
