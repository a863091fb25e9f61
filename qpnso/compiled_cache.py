"""Where qpnso's compiled code lives, and saying so when it is compiled.

Two kinds of compiled code are kept on disk, both under ``QPNSO_CACHE_DIR``
(default ``~/.cache/qpnso``):

* the C libraries of the CasADi functions (:mod:`qpnso.model.codegen`), in that folder itself, each
  named by the hash of its generated source, so they can never be stale;
* the machine code of the Numba kernels (``@njit(cache=True)`` in :mod:`qpnso.linalg`,
  :mod:`qpnso.qp.cascade`, :mod:`qpnso.qp.line`, :mod:`qpnso.qp.backends`, :mod:`qpnso.control.tick`,
  :mod:`qpnso.elbow.rom`, :mod:`qpnso.control.state`), in ``numba/<key>/``.  Numba checks a cached
  kernel against its *own* source file only, so a kernel
  that calls a kernel of another module kept the callee's old code after that module changed.
  The key therefore hashes, with the qpnso, Numba and NumPy versions, every package file a kernel
  can reach (:func:`kernel_sources`): any change to one of them gives a fresh, empty folder.  A
  user-set ``NUMBA_CACHE_DIR`` is respected: the keyed folder is then made inside it.

:func:`begin_keyed_numba_cache` (first thing in ``qpnso/__init__.py``, before any kernel module
is imported: Numba picks a kernel's cache folder when it is decorated) points
``numba.config.CACHE_DIR`` at the keyed folder; :func:`end_keyed_numba_cache` (last thing there)
puts back the user's setting, so Numba kernels of other code are not cached in qpnso's folder.
Keyed folders not used for :data:`KEEP_DAYS` days, and all but the :data:`KEEP_FOLDERS` most
recently used, are removed when a new one is made (each import marks its folder as used).

Compiling is slow the first time (:data:`NUMBA_COLD_SECONDS`, :data:`C_BYTES_PER_SECOND`):
:func:`announce_compile` tells the user, on stderr, what compiles and about how long it takes.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

log = logging.getLogger(__name__)

PACKAGE_DIR = Path(__file__).resolve().parent

NUMBA_COLD_SECONDS = 80.0
"""s: compiling every kernel the control tick uses, once per machine and kernel sources (measured:
``Controller(load_robot('lwr4p'))`` with empty caches and ``QPNSO_COMPILE=off``: 78.3 s of CPU on this 2-core
machine since the keep-out kernels are compiled too (71.3 s before them, 34.5–38.0 s before the general cascade
and the continuity interval); docs/benchmarks.md, issue 16's cold start)."""

C_BYTES_PER_SECOND = 25_000.0
"""Bytes of CasADi-generated C that ``cc -O1`` compiles per second (measured for the LWR4+'s three
functions: 120 kB in 2 s, 255 kB in 9 s, 266 kB in 11 s); gives the announced time."""

KEEP_DAYS = 30.0
"""days: a keyed Numba folder not used for this long is removed when a new one is made."""
KEEP_FOLDERS = 8
"""At most this many keyed Numba folders (the most recently used) are kept besides the current one."""

_PREFIX = "qpnso-"
_numba_dir: Path | None = None
_user_numba_dir: str | None = None


def cache_root() -> Path:
    """``QPNSO_CACHE_DIR``, default ``~/.cache/qpnso``: the folder of all of qpnso's compiled code."""
    return Path(os.environ.get("QPNSO_CACHE_DIR", Path.home() / ".cache" / "qpnso"))


_IMPORT = re.compile(
    r"^[ \t]*(?:from[ \t]+(\.*[\w.]*)[ \t]+import[ \t]+(\([^)]*\)|[^\n#]*)"
    r"|import[ \t]+([^\n#]+))",
    re.M,
)
"""An import statement: ``from <1> import <2>`` (names, maybe in parentheses) or ``import <3>``."""
_KERNELS = re.compile(r"^[ \t]*(?:(?:from|import)[ \t]+numba\b|@[\w.]*(?:jit|vectorize|cfunc|stencil)\b)", re.M)
"""A line that makes a file a kernel module: it imports Numba or decorates with a Numba compiler."""


def kernel_sources() -> list[Path]:
    """The package's files a Numba kernel can reach: every file that imports ``numba`` or decorates
    with a ``jit``/``vectorize``/``cfunc``/``stencil``, and every
    qpnso module such a file imports, transitively (a kernel sees only its own module's globals,
    which come from its code and its imports).  Other modules (the CLI, the controller, ...) can
    change without recompiling the kernels.  Import-like lines in docstrings count too: the set
    can only be too large, never too small."""
    files = {p: p.read_text(encoding="utf-8", errors="replace") for p in PACKAGE_DIR.rglob("*.py")}
    todo = [p for p, text in files.items() if _KERNELS.search(text)]
    reached: set[Path] = set()
    while todo:
        path = todo.pop()
        if path not in reached:
            reached.add(path)
            todo += _imported_files(files[path], path)
    return sorted(reached)


def _module_files(name: tuple[str, ...]) -> list[Path]:
    """Files of the qpnso module ``name`` (``("qpnso", "a", "b")``) and of the subpackages it is in,
    the package's own ``__init__`` excepted."""
    found = []
    for k in range(2, len(name) + 1):
        folder = PACKAGE_DIR.joinpath(*name[1:k])
        found += [c for c in (folder / "__init__.py", folder.with_suffix(".py")) if c.is_file()]
    return found


def _imported_files(text: str, path: Path) -> list[Path]:
    """The package's files that the import statements of ``text`` (the file ``path``) run or bind."""
    package = ("qpnso",) + path.relative_to(PACKAGE_DIR).parent.parts
    init = PACKAGE_DIR / "__init__.py"
    found: list[Path] = []
    for source, names, modules in _IMPORT.findall(text):
        if modules:  # import qpnso.a.b: binds the name qpnso, the package itself
            for module in modules.split(","):
                name = tuple(module.split()[0].split(".")) if module.split() else ()
                if name and name[0] == "qpnso":
                    found += [init] + _module_files(name)
            continue
        dots = len(source) - len(source.lstrip("."))
        base = package[: len(package) - (dots - 1)] if dots else ()
        base += tuple(source.lstrip(".").split(".")) if source.lstrip(".") else ()
        if not base or base[0] != "qpnso":
            continue
        found += _module_files(base)
        for alias in names.strip("() \n").split(","):
            words = alias.split()
            if not words:
                continue
            sub = _module_files(base + (words[0],))
            found += sub if sub else ([init] if base == ("qpnso",) else [])
    return found


def source_key(version: str) -> str:
    """Name of the Numba folder of this package's kernels: ``qpnso-<version>-numba<version>-<hash>``,
    the hash over the files of :func:`kernel_sources` (path and bytes) and the NumPy and Python
    versions."""
    h = hashlib.sha256()
    h.update(f"{np.__version__} {sys.version_info[:2]}".encode())
    for path in kernel_sources():
        h.update(path.relative_to(PACKAGE_DIR).as_posix().encode() + b"\0")
        h.update(path.read_bytes() + b"\0")
    return f"{_PREFIX}{version}-numba{numba.__version__}-{h.hexdigest()[:16]}"


def numba_cache_base() -> Path:
    """The folder holding the keyed Numba folders: ``NUMBA_CACHE_DIR`` if set, else
    ``QPNSO_CACHE_DIR/numba``."""
    user = os.environ.get("NUMBA_CACHE_DIR")
    return Path(user) if user else cache_root() / "numba"


def begin_keyed_numba_cache(version: str) -> Path:
    """Cache the Numba kernels decorated from now on in the keyed folder (created, marked as used,
    old siblings pruned); returns it.  A base folder that cannot be written falls back to the
    system's temporary folder, never to Numba's cache beside the sources."""
    global _numba_dir, _user_numba_dir
    key = source_key(version)
    folder = numba_cache_base() / key
    user = os.getuid() if hasattr(os, "getuid") else 0
    for candidate in (folder, Path(tempfile.gettempdir()) / f"qpnso-numba-{user}" / key):
        try:
            new = not candidate.is_dir()
            candidate.mkdir(parents=True, exist_ok=True)
            os.utime(candidate)  # last used: what pruning goes by
        except OSError as exc:
            log.warning("qpnso: cannot use %s for Numba's cache (%s)", candidate, exc)
            continue
        folder = candidate
        if new:
            _prune(folder)
        break
    # numba.config sets its settings at run time (from the environment): no attribute for mypy to see
    _user_numba_dir = numba.config.CACHE_DIR  # type: ignore[attr-defined]
    numba.config.CACHE_DIR = str(folder)  # type: ignore[attr-defined]
    _numba_dir = folder
    return folder


def end_keyed_numba_cache() -> None:
    """Put back Numba's cache setting (qpnso's kernels keep the keyed folder they were given)."""
    if _user_numba_dir is not None:
        numba.config.CACHE_DIR = _user_numba_dir  # type: ignore[attr-defined]


def numba_cache_dir() -> Path | None:
    """The keyed folder of qpnso's Numba kernels (None before :func:`begin_keyed_numba_cache`)."""
    return _numba_dir


def _prune(current: Path) -> None:
    """Remove sibling keyed folders unused for :data:`KEEP_DAYS` or beyond the :data:`KEEP_FOLDERS`
    most recently used (a process still using one loses nothing it has loaded)."""
    try:
        others = [p for p in current.parent.iterdir() if p.name.startswith(_PREFIX) and p != current and p.is_dir()]
        others.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    too_old = time.time() - KEEP_DAYS * 86400.0
    for rank, path in enumerate(others):
        try:
            if rank >= KEEP_FOLDERS or path.stat().st_mtime < too_old:
                shutil.rmtree(path, ignore_errors=True)
        except OSError:
            pass


def jit_disabled() -> bool:
    """True when Numba runs the kernels as Python (``NUMBA_DISABLE_JIT=1``): nothing compiles or is cached."""
    return bool(numba.config.DISABLE_JIT)  # type: ignore[attr-defined]  # (set at run time, as CACHE_DIR)


def numba_cache_is_cold() -> bool:
    """True when no kernel of this package's sources is cached yet (the keyed folder is empty or
    missing): the next :class:`qpnso.Controller` compiles them all.  False when the JIT is disabled
    (``NUMBA_DISABLE_JIT=1``: the kernels run as Python, nothing compiles)."""
    if jit_disabled():
        return False
    if _numba_dir is None or not _numba_dir.is_dir():
        return True
    return not any(_numba_dir.rglob("*.nbi"))


def announce_compile(what: str, seconds: float, note: str = "once") -> None:
    """One line on stderr: ``qpnso: compiling <what> (<note>, about <seconds> s) ...``."""
    print(f"qpnso: compiling {what} ({note}, about {max(1, round(seconds))} s) ...", file=sys.stderr, flush=True)


def announce_numba_if_cold() -> bool:
    """Say that the control tick's kernels compile now if :func:`numba_cache_is_cold`; whether it did.
    ``Controller.__init__`` calls it first (building its params already runs kernels)."""
    if not numba_cache_is_cold():
        return False
    announce_compile("the control tick's kernels for this machine", NUMBA_COLD_SECONDS)
    return True
