"""Optional packages, known before any work (issue 41).

`predict --method nuts` fitted for 12 s and then died of `ModuleNotFoundError: No module
named 'numpyro'`; `--method importance` without arviz the same after its fit. What a method
needs is known from its name: `check_method_packages` refuses it at once (`InputError`,
exit 2) with the install command. The check looks for the packages without importing them
(arviz alone takes seconds to import).
"""

from __future__ import annotations

import importlib.util
import sys

from jaxwear._core.errors import InputError

EXTRA = "bayes"
INSTALL = f'pip install "jaxwear[{EXTRA}]"'
# what each sampling method imports: numpyro (NUTS), arviz (diagnostics, PSIS), h5netcdf
# (posterior.nc)
METHOD_PACKAGES = {"nuts": ("numpyro", "arviz", "h5netcdf"),
                   "importance": ("arviz", "h5netcdf")}


def installed(name: str) -> bool:
    """Whether `import name` can find the package (a `None` in `sys.modules` is a package
    blocked from import: not installed)."""
    if name in sys.modules:
        return sys.modules[name] is not None
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def check_method_packages(method: str, where: str = "<<method>>") -> None:
    """`InputError` naming the missing packages of `method` and the install command."""
    missing = [n for n in METHOD_PACKAGES.get(method, ()) if not installed(n)]
    if missing:
        raise InputError(f"{where} {method} needs the optional package"
                         f"{'s' if len(missing) > 1 else ''} {', '.join(missing)}, not "
                         f"installed; install them with: {INSTALL} (or use <<method>> laplace)")
