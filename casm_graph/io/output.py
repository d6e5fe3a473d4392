"""All-or-nothing output: a run directory appears complete or not at all, and JSON is always strict.

Every command that writes goes through :func:`checked_out` before it computes anything (an unusable
``--out`` is one clear line, not a lost hour) and :func:`atomic_dir` when it writes: the files go into
a hidden temporary sibling that is renamed into place at the end, so a failure, a full disk or a
signal leaves ``--out`` absent (or as it was), never half written.
"""
from __future__ import annotations

import json
import math
import os
import secrets
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from casm_graph.io.log import LogError


def _inside(path: Path, other: Path) -> bool:
    """``path`` is ``other`` or lies under it."""
    return path == other or other in path.parents


def checked_out(out, force: bool = False, inputs: Iterable = ()) -> Path:
    """``out`` resolved and checked before any work: usable, empty unless ``force``, never an input's place."""
    if out is None or str(out).strip() == "":
        raise LogError("--out: give a directory to write into (an empty path would write into the working directory)")
    path = Path(out).expanduser().resolve()
    for item in inputs:
        if item is None:
            continue
        src = Path(item).expanduser().resolve()
        home = src if src.is_dir() else src.parent
        if _inside(home, path):
            raise LogError(f"--out {out}: the input {item} lives there; write somewhere else")
    if path.exists() and not path.is_dir():
        raise LogError(f"--out {out}: exists and is not a directory")
    if path.is_dir() and any(path.iterdir()) and not force:
        raise LogError(f"--out {out}: exists and is not empty; choose another directory or pass --force to replace it")
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
        raise LogError(f"--out {out}: cannot write in {parent}")
    return path


def _fresh(path: Path, kind: str) -> Path:
    """A new hidden sibling directory of ``path`` (made with the user's umask, like any directory they make)."""
    while True:
        p = path.parent / f".{path.name}.{secrets.token_hex(4)}.{kind}"
        try:
            p.mkdir()
            return p
        except FileExistsError:
            continue


_PARTIAL: set[Path] = set()            # temporary directories being written now
_SET_ASIDE: dict[Path, Path] = {}      # outputs being replaced: their place -> where they wait meanwhile


def discard_partial() -> None:
    """Remove every half-written output and put back any output that was being replaced.

    For a signal handler that must leave at once (a signal can land inside a C callback, where an
    exception raised to unwind :func:`atomic_dir` would be swallowed)."""
    for tmp in list(_PARTIAL):
        shutil.rmtree(tmp, ignore_errors=True)
    for path, old in list(_SET_ASIDE.items()):
        if not path.exists() and (old / path.name).exists():
            os.rename(old / path.name, path)
        shutil.rmtree(old, ignore_errors=True)


@contextmanager
def atomic_dir(out, force: bool = False, inputs: Iterable = ()) -> Iterator[Path]:
    """Yield an empty temporary directory; on success it replaces ``out`` in one rename, on any failure it goes."""
    path = checked_out(out, force, inputs)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _fresh(path, "partial")
    _PARTIAL.add(tmp)
    try:
        yield tmp
        for f in tmp.rglob("*"):              # the data reaches the disk before the rename makes it visible
            if f.is_file():
                with open(f, "rb") as fh:
                    os.fsync(fh.fileno())
        if path.exists():
            old = _fresh(path, "old")
            _SET_ASIDE[path] = old
            os.rename(path, old / path.name)
            os.rename(tmp, path)
            del _SET_ASIDE[path]
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        _PARTIAL.discard(tmp)


def strict(x):
    """``x`` with numpy scalars and arrays made plain and every NaN or infinity replaced by None (JSON null)."""
    if isinstance(x, dict):
        return {str(k): strict(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [strict(v) for v in x]
    if isinstance(x, np.ndarray):
        return strict(x.tolist())
    if isinstance(x, (np.bool_, bool)):
        return bool(x)
    if isinstance(x, (np.integer, int)):
        return int(x)
    if isinstance(x, (np.floating, float)):
        return float(x) if math.isfinite(x) else None
    return x


def json_text(obj) -> str:
    """Strict JSON (no NaN, no Infinity: values that are not finite are null)."""
    return json.dumps(strict(obj), indent=2, allow_nan=False)


def write_json(path, obj) -> None:
    Path(path).write_text(json_text(obj))
