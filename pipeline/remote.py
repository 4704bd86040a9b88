"""Stores on object storage: fsspec URLs (``s3://bucket/archive/capture.zarr``, ``gs://…``, ``memory://…``) in
``load_store`` and in a workflow's outputs.

zarr and xarray read and write through fsspec themselves; this module holds what selpath adds on top:

* **Credentials never come from the workflow file.** fsspec's backends take them from the standard places
  (s3fs: ``AWS_ACCESS_KEY_ID``/``AWS_SECRET_ACCESS_KEY``, ``AWS_PROFILE`` and ``~/.aws``, ``AWS_ENDPOINT_URL`` for
  an S3-compatible server; gcsfs: ``GOOGLE_APPLICATION_CREDENTIALS``), and a URL that carries a user, password
  or signed query is refused (:func:`url_problems`), so a shared workflow never leaks a key.
* **Listing instead of walking** (:func:`list_objects`): which chunks a store holds, for the checks on open.
* **A content identity without reading the bytes** (:func:`object_identity`): the SHA-256 of every object's key,
  size and ETag (S3's ETag is the MD5 of the object, or of its parts), so a changed object changes it and a
  foreign remote archive is not re-read in full to be recognised.
* ``file://`` URLs are plain local paths (:func:`local_path`), with every guarantee of local stores.

Remote outputs are written in place, manifest last: object storage has no atomic rename, so a run killed while
writing leaves a store without a completion record, which the next run replaces (never one that says it is
complete); and no lock guards them (one writer per output, as for any shared bucket).
"""

from __future__ import annotations

import hashlib
import os
from urllib.parse import urlsplit

#: query parameters that carry a secret (signed URLs, SAS tokens): refused in a workflow file
_SECRET_QUERY = ("signature", "x-amz-", "sig", "token", "key", "secret", "credential", "password")


def is_url(path: str | os.PathLike) -> bool:
    """True for a ``scheme://`` URL other than ``file://`` (which :func:`local_path` turns into a path)."""
    text = os.fspath(path)
    return "://" in text and not text.startswith("file://")


def local_path(path: str | os.PathLike) -> str:
    """``file:///x/y`` → ``/x/y``; anything else unchanged."""
    text = os.fspath(path)
    return text[len("file://"):] if text.startswith("file://") else text


def url_problems(url: str) -> list[str]:
    """Why ``url`` may not stand in a workflow file (empty: it may)."""
    parts = urlsplit(url)
    problems = []
    if parts.username or parts.password:
        problems.append(f"{parts.scheme}:// URL carries a user or password; credentials never go in a workflow file "
                        "(set them in the environment, e.g. AWS_ACCESS_KEY_ID/AWS_SECRET_ACCESS_KEY or AWS_PROFILE)")
    secret = [q.split("=", 1)[0] for q in parts.query.split("&") if q
              and any(s in q.split("=", 1)[0].lower() for s in _SECRET_QUERY)]
    if secret:
        problems.append(f"URL query {', '.join(secret)} looks like a credential; credentials never go in a workflow "
                        "file (set them in the environment or a profile)")
    if not parts.netloc and parts.scheme not in ("memory",):
        problems.append(f"URL {url!r} names no bucket or host")
    return problems


def filesystem(url: str):
    """(fsspec filesystem, path inside it) for ``url``, credentials from the environment."""
    import fsspec

    return fsspec.core.url_to_fs(url)


def list_objects(url: str, prefix: str = "") -> dict[str, dict]:
    """Every object under ``url``/``prefix``: key relative to ``url`` → fsspec's info (size, ETag …)."""
    fs, root = filesystem(url)
    base = root.rstrip("/")
    start = f"{base}/{prefix}".rstrip("/") if prefix else base
    found = fs.find(start, detail=True)
    return {name[len(base) + 1:]: info for name, info in found.items() if info.get("type", "file") == "file"}


def object_identity(url: str) -> str:
    """SHA-256 over the store's objects' keys, sizes and ETags (or modification times where a backend has no
    ETag), in sorted order: changes whenever an object's content does, without reading it."""
    digest = hashlib.sha256()
    for key, info in sorted(list_objects(url).items()):
        tag = info.get("ETag") or info.get("etag") or info.get("md5Hash") or info.get("mtime") or info.get("created")
        digest.update(f"{key}:{info.get('size')}:{tag}\n".encode())
    return digest.hexdigest()


def stamp(url: str) -> str:
    """Changes whenever the store's root metadata object is rewritten (part of dask key names)."""
    fs, root = filesystem(url)
    try:
        info = fs.info(f"{root.rstrip('/')}/zarr.json")
    except (FileNotFoundError, OSError):
        return url
    return f"{url}:{info.get('ETag') or info.get('mtime') or info.get('LastModified')}:{info.get('size')}"


def exists(url: str) -> bool:
    fs, root = filesystem(url)
    return bool(fs.exists(f"{root.rstrip('/')}/zarr.json"))


def members(url: str) -> list[str]:
    """The names directly under ``url`` (objects and prefixes); empty where nothing is there."""
    fs, root = filesystem(url)
    base = root.rstrip("/")
    try:
        return [name.rstrip("/").rsplit("/", 1)[-1] for name in fs.ls(base, detail=False)]
    except (FileNotFoundError, OSError):
        return []


def read_text(url: str, key: str) -> str | None:
    """The text of the object ``key`` under ``url``; None where there is none."""
    fs, root = filesystem(url)
    try:
        with fs.open(f"{root.rstrip('/')}/{key}", "r") as handle:
            return handle.read()
    except (FileNotFoundError, OSError):
        return None
