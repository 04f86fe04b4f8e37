"""Install a batch that someone else made (a hosted copy of a cache entry) into the batch cache, checked first.

A hosted batch is a folder holding one cache entry exactly as ``collect`` wrote it
(``<env>_<kind>_b<index>-<hash>/``: ``data/`` memmap + ``metadata.json``) and ``SHA256SUMS`` (``sha256sum``'s
format, one line per file of the entry, paths relative to the folder)::

    python -m torchrl_bail.collect --install PATH [--data-dir DIR]

Before anything is copied, :func:`check_hosted_batch` refuses the copy with one :class:`BatchValidationError`
when any of these fails, so a partial or altered copy never trains:

1. **content checksum**: every file of the entry is listed in ``SHA256SUMS`` with its digest, and no file is
   missing or unlisted;
2. **recipe hash**: the folder's ``-<hash>`` suffix, ``metadata["recipe_hash"]`` and the hash of
   ``metadata["identity"]`` (:func:`~torchrl_bail.data.cache.stable_hash`, as :func:`recipe_hash` computes it
   from a config) are one value, so ``python -m torchrl_bail.train +exp=...`` finds the entry by its recipe;
3. **the data itself**: the batch loads (:func:`~torchrl_bail.data.batch.load_batch` validates its format) and its
   transition count, episode count and mean episode return, recomputed from the rewards, equal the metadata's.

The checked entry is copied into a hidden scratch folder of the data directory and renamed into place in one step:
an interrupted install leaves nothing that loads as a batch. An entry of that name already in the cache is checked
against the source's ``SHA256SUMS`` (every file, none missing or unlisted) and reported, not copied again.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path

from torchrl_bail.data.batch import BatchValidationError, batch_statistics, load_batch
from torchrl_bail.data.cache import data_dir_of, stable_hash

__all__ = ["CHECKSUMS", "check_hosted_batch", "install_batch"]

#: the checksum file beside a hosted entry
CHECKSUMS = "SHA256SUMS"


def _sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def _entry_of(source: Path) -> Path:
    """The one cache entry (a folder with ``metadata.json``) inside ``source``, or ``source`` itself."""
    if (source / "metadata.json").is_file():
        return source
    entries = sorted(p for p in source.iterdir() if p.is_dir() and (p / "metadata.json").is_file())
    if len(entries) != 1:
        raise BatchValidationError(f"{source}: expected one batch folder (<name>-<hash>/ with metadata.json), "
                                   f"found {len(entries)}")
    return entries[0]


def _read_checksums(sums: Path) -> dict[str, str]:
    listed = {}
    for number, line in enumerate(sums.read_text().splitlines(), 1):
        if not line.strip():
            continue
        digest, _, name = line.partition("  ")
        if len(digest) != 64 or not name:
            raise BatchValidationError(f"{sums}:{number}: not a sha256sum line: {line!r}")
        listed[os.path.normpath(name)] = digest
    return listed


def _check_checksums(sums: Path, entry: Path) -> None:
    """Every file under ``entry`` matches its ``sums`` line (names ``<entry name>/...``), none missing or unlisted."""
    if not sums.is_file():
        raise BatchValidationError(f"{sums.parent}: no {CHECKSUMS} beside the batch; a hosted batch must carry one")
    listed = _read_checksums(sums)
    files = {os.path.join(entry.name, str(p.relative_to(entry))): p for p in entry.rglob("*") if p.is_file()}
    missing = sorted(set(listed) - set(files))
    unlisted = sorted(set(files) - set(listed))
    if missing or unlisted:
        raise BatchValidationError(f"{entry}: the copy is not whole: missing {missing or 'none'}, "
                                   f"not in {CHECKSUMS} {unlisted or 'none'}")
    for name in sorted(listed):
        found = _sha256(files[name])
        if found != listed[name]:
            raise BatchValidationError(f"{files[name]}: sha256 {found[:12]}... does not match {CHECKSUMS} "
                                       f"({listed[name][:12]}...): the file was altered or is incomplete")


def _check_recipe_hash(entry: Path, meta: dict) -> None:
    suffix = entry.name.rpartition("-")[2]
    of_identity = stable_hash(meta["identity"]) if "identity" in meta else None
    if not (suffix == meta.get("recipe_hash") == of_identity):
        raise BatchValidationError(f"{entry}: recipe hash disagrees: folder suffix {suffix!r}, metadata "
                                   f"recipe_hash {meta.get('recipe_hash')!r}, hash of its identity {of_identity!r}")


def _check_statistics(entry: Path, meta: dict) -> None:
    found = batch_statistics(load_batch(entry).data)
    for key in ("num_transitions", "num_episodes"):
        if found[key] != meta.get(key):
            raise BatchValidationError(f"{entry}: {key} is {found[key]} in the data, {meta.get(key)} in its metadata")
    mean, recorded = found["episode_return_mean"], meta.get("episode_return_mean")
    if not isinstance(recorded, (int, float)) or not math.isclose(mean, recorded, rel_tol=1e-9, abs_tol=1e-9):
        raise BatchValidationError(f"{entry}: mean episode return is {mean!r} in the data, {recorded!r} in its "
                                   "metadata")


def check_hosted_batch(source: str | os.PathLike) -> Path:
    """Checks the hosted batch at ``source`` (see the module docstring); returns its entry folder."""
    source = Path(source)
    if not source.is_dir():
        raise BatchValidationError(f"{source}: no such folder")
    entry = _entry_of(source)
    _check_checksums(entry.parent / CHECKSUMS, entry)
    try:
        meta = json.loads((entry / "metadata.json").read_text())
    except json.JSONDecodeError as err:
        raise BatchValidationError(f"{entry / 'metadata.json'}: not JSON ({err})") from err
    _check_recipe_hash(entry, meta)
    _check_statistics(entry, meta)
    return entry


def install_batch(source: str | os.PathLike, data_dir: str | os.PathLike | None = None) -> tuple[Path, bool]:
    """Checks the hosted batch at ``source`` and copies it into ``data_dir`` (default: the cache's).

    Returns ``(path, copied)``: the entry's path in the cache and whether it was copied (``False``: an entry of that
    name was there already and passed the same checks against the source's checksums). Raises
    :class:`BatchValidationError` for a copy that fails a check.
    """
    entry = check_hosted_batch(source)
    root = data_dir_of(None, data_dir)
    target = root / entry.name
    if target.exists():
        _check_checksums(entry.parent / CHECKSUMS, target)
        return target, False
    root.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(prefix=f".install-{entry.name}.", dir=root))
    try:
        shutil.copytree(entry, scratch / entry.name, copy_function=shutil.copy2)
        for path in [scratch / entry.name, *(scratch / entry.name).rglob("*")]:
            path.chmod(path.stat().st_mode | 0o200)  # a read-only source must not make a read-only cache entry
        os.replace(scratch / entry.name, target)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return target, True
