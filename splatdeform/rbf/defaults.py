"""Defaults of ``fit.tolerance`` and ``fit.max_centers``, chosen from the measured table in the
README (``benchmarks/fit_table.py`` re-measures it): at them every shared scan and splat file and
every generated benchmark scene converges within 3% of the exact interpolant. A module of its
own so the config layer reads them without importing the fitter (scipy.linalg)."""

DEFAULT_TOLERANCE = 1.5e-4
DEFAULT_MAX_CENTERS = 2000
