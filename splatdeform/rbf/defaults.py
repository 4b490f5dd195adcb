"""Defaults of ``fit.tolerance``, ``fit.max_centers``, ``fit.method`` and ``fit.thinning``, chosen
from the measured fit table (docs/benchmarks.md, "The table behind the defaults";
``benchmarks/fit_table.py`` re-measures it): at them every
shared scan and splat file and every generated benchmark scene converges, within 3% of the exact
interpolant. A module of its own so the config layer reads them without importing the fitter
(scipy.linalg)."""

DEFAULT_TOLERANCE = 1.5e-4
DEFAULT_MAX_CENTERS = 2000

#: ``fit.method``: ``auto`` picks the cheapest of the incremental fit, the dense solve through
#: the kept constraints (checked at every ring point) and the exact solve.
DEFAULT_METHOD = "auto"
#: ``fit.thinning``: voxel cell of each ring's thinning, in units of the ring's width
#: (:mod:`splatdeform.deform.thin`); 0 keeps every ring point.
DEFAULT_THINNING = 1.0
