"""Where the data shipped with qpnso are: the robot descriptions, the scenario files, the solver
benchmark's committed problem set and the experiments' pre-registration.

In the source tree they are folders at its top (``models/``, ``examples/scenarios/``, ``solvers/problems/``,
``docs/preregistration/``); a wheel carries them inside the package, as ``qpnso/_models/``,
``qpnso/_scenarios/``, ``qpnso/_solver_problems/``, ``qpnso/_preregistration/`` (``CMakeLists.txt`` installs the folders
onto these subpackages, with the files of :data:`SHIPPED`).  :func:`shipped_dir` finds them either way: an
installed wheel, a source tree on ``sys.path`` or an editable install.

This module uses the standard library only: ``CMakeLists.txt`` reads :data:`SHIPPED` from it (runpy) before qpnso's
dependencies are installed.
"""

from __future__ import annotations

from pathlib import Path

SHIPPED: dict[str, tuple[str, tuple[str, ...]]] = {
    "models": ("models", ("*.urdf", "*.json", "README.md")),
    "scenarios": ("examples/scenarios", ("*.toml",)),
    "solver_problems": ("solvers/problems", ("quick.npz",)),
    "preregistration": ("docs/preregistration", ("*.toml",)),
}
"""name: (its folder in the source tree, relative to the top; the files of it a wheel carries).
``solvers/problems/full.npz`` is recorded on demand, not committed, and not shipped."""

PACKAGE_DIR = Path(__file__).resolve().parent


def shipped_dir(name: str) -> Path:
    """The folder of the shipped data ``name`` (a key of :data:`SHIPPED`): ``qpnso/_<name>`` of an installed
    wheel, else the source tree's folder (qpnso run from a checkout or an editable install)."""
    installed = PACKAGE_DIR / f"_{name}"
    return installed if installed.is_dir() else PACKAGE_DIR.parent / SHIPPED[name][0]
