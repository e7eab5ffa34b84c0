"""The user cache: its folder and its atomic writes.

Everything fabkit generates once and loads later lives here: the formulas' generated
functions (:mod:`fabkit.expr_cache`, subfolder ``formulas``), the simulator's compiled
engines and surfaces (:mod:`fabkit.physics.engine.codegen`) and the toolpath's kernels
(:mod:`fabkit.toolpath.finish.kernels`).

Folder: ``FABKIT_CACHE_DIR`` if set, else the user cache (``$XDG_CACHE_HOME/fabkit`` or
``~/.cache/fabkit`` on Linux, ``~/Library/Caches/fabkit`` on macOS,
``%LOCALAPPDATA%\\fabkit\\Cache`` on Windows), subfolder ``engine``. Never the repository
or site-packages. Deleting the folder is always safe.

This module imports nothing of fabkit: the formula layer (:mod:`fabkit.expr`,
:mod:`fabkit.expr_cache`) and the engine's code generator both stand on it, so neither
needs the other for a path.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def cache_dir() -> Path:
    """The folder of generated and compiled engines (created on demand)."""
    env = os.environ.get("FABKIT_CACHE_DIR")
    if env:
        base = Path(env).expanduser()
    elif sys.platform == "darwin":
        base = Path.home() / "Library" / "Caches" / "fabkit"
    elif os.name == "nt":
        base = Path(os.environ.get("LOCALAPPDATA", Path.home() / "AppData" / "Local")) / "fabkit" / "Cache"
    else:
        base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fabkit"
    return base / "engine"


def replace_quietly(path: Path, text: str) -> bool:
    """Write ``text`` to ``path`` atomically (a temporary renamed over it), for the cache:
    False, with nothing left behind, where the cache cannot be written."""
    tmp = path.parent / f".{path.name}.{os.getpid()}.tmp"
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_text(text)
        os.replace(tmp, path)
        return True
    except OSError:
        try:
            tmp.unlink()
        except OSError:
            pass
        return False
