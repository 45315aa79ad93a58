"""Where the lab's files live: a local folder or any fsspec store (``s3://bucket/prefix``, ``gs://…``,
``memory://…``), and how an entry is published whole on either.

A local lab is a ``pathlib.Path``; a store is a ``upath.UPath`` (fsspec's pathlib), so code that joins,
globs, opens and reads paths works on both. Credentials come from the store's standard environment and
configuration (for S3: ``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, ``AWS_PROFILE``, ``~/.aws/``,
``AWS_ENDPOINT_URL`` for MinIO and other S3-compatible stores), never from vslab's files or cards.

Publication (datasets, models, cache entries, sessions): the entry's files are written into a fresh local
folder first, then
- on a local lab the folder is renamed into place in one step;
- on a store every file is uploaded, its manifest (the card or record that describes the entry) last.
  Readers take an entry only when its manifest is there, so a half-uploaded one is never visible, and a
  crashed upload is overwritten by the next with the same content (entries are content-addressed).
Recordings are always written to a local folder (a network stall must not cost a sample) and published
to a store afterwards.
"""

from __future__ import annotations

import fnmatch
import os
import shutil
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeAlias

from upath import UPath

from acquisition.errors import AcquisitionError

LabPath: TypeAlias = Path  # a local Path or a UPath: both join with "/", glob, open, read and write


class StoreError(AcquisitionError, OSError):
    """A lab store that cannot be used: its fsspec backend is not installed, it does not answer, the
    bucket does not exist or the credentials are refused. The message names the URL and what to do."""


S3 = ("s3", "s3a")  # the protocols vslab's [s3] extra serves


def is_url(text: str | os.PathLike) -> bool:
    """Does ``text`` name a store (``protocol://…``) rather than a local path? (``file://`` is local.)"""
    return isinstance(text, str) and "://" in text and not text.startswith("file://")


def lab_path(where: str | os.PathLike) -> LabPath:
    """A local folder as a ``Path``, a store URL (or a UPath) as a ``UPath``. A store whose fsspec backend is
    not installed: :class:`StoreError` naming the package to install."""
    if isinstance(where, UPath | Path):  # a local UPath is a Path too
        return where
    text = os.fspath(where)
    if text.startswith("file://"):
        return Path(text.removeprefix("file://"))
    if not is_url(text):
        return Path(text)
    try:
        path = UPath(text)
        path.fs  # noqa: B018 - the backend is imported here, so a missing one is said here
        return path
    except (ImportError, ValueError) as exc:  # fsspec: "Install s3fs to access S3"; an unknown protocol
        protocol = text.split("://", 1)[0]
        hint = "pip install 'vslab[s3]'" if protocol in S3 else f"install fsspec's backend for {protocol}://"
        raise StoreError(f"{text}: cannot open this store ({_first_line(exc)}; {hint})") from None


def as_path(path: str | os.PathLike) -> LabPath:
    """A file or folder a reader was given: a ``Path`` or ``UPath`` as it is, text as a local ``Path``. (A
    lab's root and its stores come from ``pipeline.lab.Lab``, which opens URLs; a reader never does.)"""
    return path if isinstance(path, UPath | Path) else Path(os.fspath(path))


def is_local(path: LabPath) -> bool:
    """Is ``path`` on this computer's file system (rename is atomic there)?"""
    return isinstance(path, Path)


def published(entry: LabPath, manifest: str) -> bool:
    """Is ``entry`` a whole entry a reader may take? Locally every folder is (it was renamed in whole); on
    a store only one whose manifest was uploaded (the others are uploads in progress or abandoned)."""
    return is_local(entry) or (entry / manifest).is_file()


PROBE_TIMEOUT_S = 5.0  # connect and read timeouts of the store check: the store is there, or one line soon


def check_store(root: LabPath) -> None:
    """Raise :class:`StoreError` unless the store under ``root`` answers and its bucket may be listed
    (nothing to do for a local folder). One request, one attempt, within about ``PROBE_TIMEOUT_S`` s: a
    listing of the bucket's top level."""
    if is_local(root):
        return
    bucket = root.path.split("/", 1)[0]
    try:
        _probe_fs(root).ls(bucket, detail=False)
    except FileNotFoundError:
        raise StoreError(f"{root}: the bucket {bucket!r} does not exist (create it first)") from None
    except Exception as exc:  # botocore's, aiohttp's and fsspec's own errors: no common base to catch
        why = _first_line(exc)
        raise StoreError(f"{root}: the store does not answer or refuses access ({why})") from None


def _probe_fs(root: LabPath):
    """``root``'s file system for one quick check: on S3 a client of its own without botocore's and s3fs's
    retries and with short timeouts (a store that is not there takes minutes to say so otherwise); the
    lab's own client, which the real work uses, keeps the libraries' retries."""
    fs = root.fs
    if root.protocol not in S3:
        return fs
    options = dict(fs.storage_options)
    config = {**options.pop("config_kwargs", {}), "connect_timeout": PROBE_TIMEOUT_S,
              "read_timeout": PROBE_TIMEOUT_S, "retries": {"total_max_attempts": 1}}  # fmt: skip
    probe = type(fs)(**options, config_kwargs=config, skip_instance_cache=True)
    probe.retries = 1  # s3fs's own retries of a timed-out read (a class attribute, not an argument)
    return probe


def publish(final: LabPath, fill: Callable[[Path], None], manifest: str) -> bool:
    """Write the entry ``final`` whole: ``fill(folder)`` writes its files into a fresh local folder, which
    then becomes ``final`` (see the module's docstring); ``manifest`` is the file ``fill`` writes that
    describes the entry. False, and nothing changed, where ``final`` was published before (another writer
    got there first: theirs stays)."""
    if (final / manifest).is_file():
        return False
    local = is_local(final)
    if local:
        final.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}-", dir=final.parent if local else None))
    try:
        fill(tmp)
        if not (tmp / manifest).is_file():
            raise ValueError(f"{final}: the entry's writer made no {manifest}")
        if local:
            try:
                os.rename(tmp, final)
            except OSError:
                if final.exists():  # another process renamed the same entry in first
                    return False
                raise
        else:
            upload(tmp, final, manifest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return True


def upload(folder: Path, final: LabPath, manifest: str) -> None:
    """Copy the local ``folder`` to the store entry ``final``, the manifest last (its presence publishes);
    ``manifest`` may be a pattern (``*.json``: every record after every file it describes)."""
    files = sorted(p for p in folder.rglob("*") if p.is_file())
    last = [p for p in files if fnmatch.fnmatch(p.relative_to(folder).as_posix(), manifest)]
    for path in [p for p in files if p not in last] + last:
        final.fs.put_file(str(path), final.joinpath(*path.relative_to(folder).parts).path)


def write_parquet(df, path: Path) -> None:
    """Write ``df`` (a DataFrame, without its index) as the Parquet file ``path``, each data page with its
    CRC-32 (Parquet's page checksum, which pyarrow leaves out unless asked): :func:`read_parquet` then
    refuses a file whose bytes changed after it was written, instead of reading other numbers."""
    df.to_parquet(path, index=False, write_page_checksum=True)


def read_parquet(path: LabPath, columns: list[str] | None = None):
    """A Parquet file of a local lab or a store as a DataFrame (pandas reads a local one by its path, a
    store's from the open file). Each page's checksum is verified where the file has them
    (:func:`write_parquet`): a damaged page is an ``OSError`` ("CRC checksum verification failed"), not
    numbers read from flipped bits. (Files written before the checksums read as before, unverified.)"""
    import pandas as pd

    if is_local(path):
        return pd.read_parquet(path, columns=columns, page_checksum_verification=True)
    with path.open("rb") as f:
        return pd.read_parquet(f, columns=columns, page_checksum_verification=True)


def remove(entry: LabPath) -> None:
    """Remove the folder ``entry`` and all it holds (a local folder or a store's prefix); nothing where it
    is not there."""
    if is_local(entry):
        shutil.rmtree(entry, ignore_errors=True)
    elif entry.exists():
        entry.fs.rm(entry.path, recursive=True)


@contextmanager
def local_folder(where: LabPath) -> Iterator[Path]:
    """A local folder standing for ``where``: itself when it is local; a temporary folder otherwise (the
    caller publishes what it wants kept)."""
    if is_local(where):
        yield where
        return
    with tempfile.TemporaryDirectory(prefix="vslab-stage-") as tmp:
        yield Path(tmp)


@contextmanager
def fetched(folder: LabPath) -> Iterator[Path]:
    """``folder`` as a local folder of the same name: itself when local; for a store, a temporary copy
    fetched whole (one request per file: a reader that opens each file several times, seeking, would make a
    request each time), removed afterwards."""
    if is_local(folder):
        yield folder
        return
    with tempfile.TemporaryDirectory(prefix="vslab-fetch-") as tmp:
        here = Path(tmp) / folder.name
        here.mkdir()
        for entry in folder.fs.ls(folder.path, detail=True):  # one listing, then one GET per file
            if entry["type"] == "file":
                name = entry["name"].rstrip("/").rsplit("/", 1)[-1]
                folder.fs.get_file(entry["name"], str(here / name))
        yield here


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
