"""Writing a store aside and publishing it whole: the replace protocol.

A store, a term of the inverse or a scene is built in a hidden sibling directory
(:func:`temporary_sibling`) and renamed into place (:func:`move_into_place`); a process
killed half way leaves a sibling that :func:`recover_interrupted_replace` (run by every
writer and by :func:`bigT.storage.open`) puts back or deletes. Small metadata files are
replaced whole (:func:`bigT.atomic.atomic_write_json`): the root attributes
(:func:`write_root_attrs`) and the redirect that publishes a versioned store's current
term (:func:`set_redirect`). Readers see the old state or the new one, never a mix.
"""

from __future__ import annotations

import contextlib
import os
import shutil
from pathlib import Path, PurePosixPath

from .. import config
from ..atomic import dead_writers_siblings, fsync_dir, fsync_tree, hidden_sibling
from ..errors import IncompleteStoreError, StoreError
from . import _format as fmt
from .attrs import StoreAttrs, read_raw_attrs
from .objects import ObjectPath, as_location


def durable() -> bool:
    """Whether the store writers fsync what they publish: ``config.DURABILITY`` (read
    at each call, so a command's ``--durability`` holds for its run), the one place
    that decides. Any value but "none" is "full": a misspelling never drops them."""
    return config.DURABILITY != "none"


def is_bigt_or_empty(path: Path) -> bool:
    if path.is_dir() and not any(path.iterdir()):
        return True
    try:
        read_raw_attrs(path)
        return True
    except StoreError:
        return False


def remove_tree(path) -> None:
    """Delete the directory (or the objects below the prefix) ``path``, what is
    missing ignored; a symbolic link is deleted as itself."""
    if isinstance(path, ObjectPath):
        path.remove_tree()
    elif os.path.islink(path):
        os.unlink(path)
    else:
        shutil.rmtree(path, ignore_errors=True)


def remove_existing(path: Path, overwrite: bool) -> None:
    """Refuse an existing path unless ``overwrite``; never delete what is not a bigT store."""
    if path.exists():
        check_replaceable(path, overwrite)
        if isinstance(path, ObjectPath):
            path.remove_tree()
        else:
            shutil.rmtree(path)


def check_replaceable(path: Path, overwrite: bool) -> None:
    """Refuse an existing ``path`` unless ``overwrite``, and refuse to replace anything
    that is not a bigT store (or an empty directory) even then. Deletes nothing of
    the user's (a replace killed half way is recovered first: the old store back)."""
    recover_interrupted_replace(path)
    if path.exists():
        if not overwrite:
            raise StoreError("already exists; pass {option} to replace it", path,
                             option=("overwrite", True))
        if not is_bigt_or_empty(path):
            raise StoreError("exists and is not a bigT store; refusing to overwrite it", path)


def temporary_sibling(path: Path) -> Path:
    """A fresh hidden directory name beside ``path`` to build a replacement in."""
    return hidden_sibling(Path(path), "partial")


def move_into_place(tmp: Path, path: Path) -> None:
    """Replace ``path`` (absent, or a bigT store) by the complete directory ``tmp``.

    Two renames on the same file system; if the second fails the old store is renamed
    back, so ``path`` is never left missing or half replaced. (Object storage has no
    rename: :func:`bigT.storage.writer.built_aside` builds there in place.) A process killed between
    the two leaves ``path`` missing and the old store in a hidden ``.old`` sibling:
    :func:`recover_interrupted_replace` (run by every writer and by ``open``) puts it
    back.

    Durably (``config.DURABILITY``): everything in ``tmp`` is fsynced before the
    rename (a pass that costs little where its writers fsynced already, and covers
    those that did not), the parent directory after it.
    """
    if durable():
        fsync_tree(tmp)
    if not path.exists():
        os.replace(tmp, path)
        if durable():
            fsync_dir(path.parent)
        return
    old = hidden_sibling(path, "old")
    os.replace(path, old)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.replace(old, path)
        raise
    if durable():
        fsync_dir(path.parent)  # the new store in place before the old one is deleted
    # renamed again before the deletion: a ".old" is always whole (restorable), a
    # ".trash" may be half deleted (never restored)
    trash = old.with_name(old.name[:-len("old")] + "trash")
    os.replace(old, trash)
    shutil.rmtree(trash, ignore_errors=True)


def recover_interrupted_replace(path) -> None:
    """Undo what a writer killed during :func:`move_into_place` or while building a
    replacement left beside ``path``: a missing ``path`` gets its old store back from
    the ``.old`` sibling; ``.old``, ``.partial`` and ``.trash`` siblings of dead
    writers are deleted. Siblings of writers still running are left alone."""
    path = as_location(path)
    if isinstance(path, ObjectPath) or not path.parent.is_dir():
        return  # nothing is renamed in object storage, so nothing is left beside it
    old = dead_writers_siblings(path.parent, "old", path.name)
    if old and not path.exists():
        with contextlib.suppress(OSError):  # another process may have restored it
            os.rename(old.pop(0), path)
    for kind in ("partial", "trash"):
        old += dead_writers_siblings(path.parent, kind, path.name)
    for entry in old:
        shutil.rmtree(entry, ignore_errors=True)


def write_root_attrs(path: Path, attrs: StoreAttrs, sync: bool = True) -> None:
    """Set ``attributes["bigT"]`` of the root ``zarr.json`` of the store at ``path`` to
    ``attrs``, keeping any other attributes, atomically (:func:`atomic_write_json`;
    fsynced unless ``sync`` is False or ``config.DURABILITY`` says none)."""
    meta_path = as_location(path) / "zarr.json"
    meta = fmt.read_json(meta_path) if meta_path.is_file() else fmt.group_json({})
    meta.setdefault("attributes", {})[fmt.ATTRS_KEY] = attrs.to_dict()
    fmt.write_json(meta_path, meta, sync and durable())


def set_redirect(path, target: str, attributes: dict | None = None) -> None:
    """Point the versioned store at ``path`` to its sub-store ``target``, atomically.

    The inverse engine writes term k into e.g. ``path/terms/k`` with a
    :class:`BlockCSRWriter`, finalizes it, then calls ``set_redirect(path, "terms/k")``:
    a reader opening ``path`` sees the old term or the new one, never a mix.

    Parameters
    ----------
    path : str or os.PathLike
        Root directory (created, with a group zarr.json, when missing).
    target : str
        Relative POSIX path of a complete bigT store inside ``path``.
    attributes : dict, optional
        Other attributes of the root set in the same write as the flip (the inverse
        store's record, :meth:`bigT.storage.InverseStore.publish`): one atomic, durable
        replace of ``zarr.json`` instead of two, and no state between them to repair.
    """
    root = as_location(path)
    dest = fmt.redirect_target(target, root)
    attrs = read_raw_attrs(dest)
    if "redirect" in attrs:
        raise StoreError(f"redirect target {target!r} is itself a redirect", root)
    if not attrs.get("complete"):
        raise IncompleteStoreError(f"redirect target {target!r} is not a finalized store", root)
    root.mkdir(parents=True, exist_ok=True)
    # Make every level between root and target an explicit zarr v3 group, so another
    # zarr implementation can walk the hierarchy.
    level = root
    for part in PurePosixPath(target).parts[:-1]:
        level = level / part
        if not (level / "zarr.json").is_file():
            fmt.write_json(level / "zarr.json", fmt.group_json({}), durable())
    meta_path = root / "zarr.json"
    meta = fmt.read_json(meta_path) if meta_path.is_file() else fmt.group_json({})
    if meta.get("node_type") != "group":
        raise StoreError("cannot set a redirect: zarr.json is not a group", root)
    bigt = dict((meta.get("attributes") or {}).get(fmt.ATTRS_KEY) or {})
    if bigt and bigt.get("format") != fmt.FORMAT_NAME:
        raise StoreError("cannot set a redirect: attrs['bigT'] belongs to another format", root)
    bigt.update({"format": fmt.FORMAT_NAME, "version": fmt.FORMAT_VERSION,
                 "redirect": PurePosixPath(target).as_posix()})
    if attributes and fmt.ATTRS_KEY in attributes:
        raise ValueError(f"attributes[{fmt.ATTRS_KEY!r}] is the redirect's own")
    meta.setdefault("attributes", {}).update(attributes or {})
    meta["attributes"][fmt.ATTRS_KEY] = bigt
    # the target's files were fsynced when it was finalized; the names that lead to it
    # (a term directory made by mkdir) are made durable here, before the flip points
    # at them (config.DURABILITY)
    local = not isinstance(root, ObjectPath)
    for level in [dest.parent, *dest.parent.parents] if durable() and local else []:
        fsync_dir(level)
        if level == root:
            break
    fmt.write_json(meta_path, meta, durable())


def write_group(path, attributes: dict) -> None:
    """Make ``path`` a zarr v3 group holding ``attributes``, its zarr.json replaced
    whole (created with its parents when missing): the groups around the stores, such
    as a scene's ``ground_truth/``."""
    path = as_location(path)
    path.mkdir(parents=True, exist_ok=True)
    fmt.write_json(path / "zarr.json", fmt.group_json(attributes), durable())
