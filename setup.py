"""What ``pyproject.toml`` cannot say: the code packages are found (``qpnso*``), and the data the library reads
at run time, kept in folders at the top of the source tree, are shipped inside the package as the subpackages
``qpnso._<name>`` (:data:`qpnso.shipped.SHIPPED`; :func:`qpnso.shipped.shipped_dir` finds them).  A folder outside
the package can only be shipped by mapping it with ``package_dir``, and ``pyproject.toml``'s ``packages.find``
cannot add a mapped package to the ones it finds."""

import runpy
from pathlib import Path

from setuptools import find_packages, setup

SHIPPED = runpy.run_path(str(Path(__file__).resolve().parent / "qpnso" / "shipped.py"))["SHIPPED"]
DATA = {f"qpnso._{name}": folder for name, (folder, _) in SHIPPED.items()}

setup(
    packages=find_packages(include=["qpnso", "qpnso.*"]) + sorted(DATA),
    package_dir=DATA,
    package_data={"qpnso": ["py.typed"], **{f"qpnso._{name}": list(files) for name, (_, files) in SHIPPED.items()}},
)
