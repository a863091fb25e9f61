"""Whether anything compiles after the constructor: :class:`KernelWatch` keeps the signatures of every Numba
kernel (``numba.core.registry.CPUDispatcher``) of qpnso's imported modules and says which were added since.

A kernel called with argument types it has no machine code for compiles them, or loads them from Numba's cache
(issue 31, item 4: a Fortran-ordered rotation reaching ``store_interval`` in a Panda tick: 15–22 ms of CPU in
every new process, 959 ms when the cache lacks it): either way its dispatcher gains a signature.  The fuzz takes
the signatures after the controllers are built and checks them after every ``step`` call.
"""

from __future__ import annotations

import sys

from numba.core.registry import CPUDispatcher

_ARGUMENT_CHARS = 60
"""A signature's argument types are cut to this many characters (a record's type names every field)."""


def qpnso_dispatchers() -> dict[str, CPUDispatcher]:
    """Every Numba kernel reachable as a module attribute of an imported ``qpnso`` module, by name (its own module
    and name when it is qpnso's, else where it was found)."""
    found: dict[int, tuple[str, CPUDispatcher]] = {}
    for module_name, module in sorted(sys.modules.items()):
        if module is None or not (module_name == "qpnso" or module_name.startswith("qpnso.")):
            continue
        for attribute, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher) and id(value) not in found:
                own = getattr(value.py_func, "__module__", "") or ""
                name = (
                    f"{own}.{value.py_func.__qualname__}" if own.startswith("qpnso") else f"{module_name}.{attribute}"
                )
                found[id(value)] = (name, value)
    return dict(found.values())


def signature_text(signature: tuple) -> str:
    """A signature's argument types, each cut to :data:`_ARGUMENT_CHARS` characters."""
    parts = [str(t) if len(str(t)) <= _ARGUMENT_CHARS else str(t)[: _ARGUMENT_CHARS - 3] + "..." for t in signature]
    return "(" + ", ".join(parts) + ")"


class KernelWatch:
    """The signatures of qpnso's Numba kernels at a baseline (:meth:`rebase`: after a constructor), and which
    were added since (:meth:`added`).  ``added`` checks the known kernels' overload counts (about 10 µs), so it
    can run after every tick; ``full=True`` walks the modules again, for kernels of modules imported since."""

    def __init__(self) -> None:
        self._kernels: dict[str, CPUDispatcher] = {}
        self._counts: dict[str, int] = {}
        self._overloads: list[dict] = []  # each kernel's own dict of compiled signatures (Numba adds to it)
        self._total = 0
        self.rebase()

    def rebase(self) -> None:
        """The current signatures become the baseline."""
        self._kernels = qpnso_dispatchers()
        self._counts = {name: len(d.overloads) for name, d in self._kernels.items()}
        self._overloads = [d.overloads for d in self._kernels.values()]
        self._total = sum(self._counts.values())

    def added(self, full: bool = False) -> list[str]:
        """``kernel(argument types)`` of each signature added since the last call (or the baseline); they become
        the baseline."""
        if full:
            for name, dispatcher in qpnso_dispatchers().items():
                if name not in self._kernels:
                    self._kernels[name], self._counts[name] = dispatcher, 0
                    self._overloads.append(dispatcher.overloads)
        total = sum(map(len, self._overloads))
        if total == self._total:
            return []
        self._total = total
        out = []
        for name, dispatcher in self._kernels.items():
            count = len(dispatcher.overloads)
            if count != self._counts[name]:
                new = list(dispatcher.signatures)[self._counts[name] :]
                out += [f"{name}{signature_text(sig)}" for sig in new]
                self._counts[name] = count
        return out
