"""The deformation basis b(p), grad b(p) and the backend dispatcher.

Backends: ``numpy`` (:mod:`.reference`, float64, the oracle), ``opencl`` (:mod:`.opencl`,
float32 results accumulated in double) and ``auto`` (OpenCL when a device exists, else numpy
with one warning).
"""

from __future__ import annotations

import threading
import warnings

import numpy as np

from ..errors import InputError, NoDeviceWarning
from ..rbf.result import RbfFit
from .names import BACKENDS
from .result import Basis

__all__ = ["BACKENDS", "Basis", "compute_basis", "resolve_backend", "warm_up"]

_WARM: threading.Thread | None = None


def warm_up(backend: str = "auto", device: str | None = None, k: int | None = None,
            gradients: bool = True) -> None:
    """Start opening the OpenCL device of ``backend`` / ``device`` on a background thread:
    import pyopencl, find the device, create its context and build (or load from pyopencl's
    cache) the kernel for ``k`` basis columns (with gradients when asked: the one-shot
    evaluation of a model without normals needs none). ``deform`` calls this once its
    input has loaded, so the 0.1-0.2 s this takes runs beside the rings and the fit instead
    of in the basis stage; :func:`compute_basis` waits for it. Nothing for ``numpy``; any failure
    is left for the real call to report (a missing device, a bad ``device`` name)."""
    global _WARM
    if backend not in ("auto", "opencl") or _WARM is not None:
        return

    def work() -> None:
        try:
            from . import opencl

            opencl.prepare_device(device, k, gradients)
        except Exception:  # noqa: BLE001 - reported by the compute_basis that needs it
            pass

    # not a daemon: an edit refused while the device opens (a region error from the rings)
    # exits after it; a daemon thread inside the OpenCL driver at exit aborts the process
    # ("terminate called without an active exception", exit -6) after the error line
    _WARM = threading.Thread(target=work, name="opencl-warm-up", daemon=False)
    _WARM.start()


def _wait_warm() -> None:
    warm = _WARM
    if warm is not None and warm is not threading.current_thread():
        warm.join()


def resolve_backend(backend: str = "auto", device: str | None = None) -> str:
    """The concrete backend ("numpy" or "opencl") that ``backend`` means on this machine.

    "auto" falls back to "numpy" with one ``warnings.warn`` line when no OpenCL device exists;
    "opencl" without a device raises DeviceError; anything else raises InputError.
    """
    if backend not in BACKENDS:
        raise InputError(f"backend: expected one of {', '.join(BACKENDS)}, got {backend!r}")
    if backend == "numpy":
        return "numpy"
    _wait_warm()
    from . import opencl

    if backend == "opencl":
        opencl.describe_device(device)  # raises DeviceError with the install hint
        return "opencl"
    if opencl.opencl_available(device):
        return "opencl"
    warnings.warn(
        f"backend 'auto': no OpenCL device found, using the numpy reference (slow); "
        f"{opencl.NO_DEVICE_HINT}",
        NoDeviceWarning,
        stacklevel=3,
    )
    return "numpy"


def compute_basis(
    points: np.ndarray,
    fit: RbfFit,
    *,
    gradients: bool = True,
    backend: str = "auto",
    device: str | None = None,
) -> Basis:
    """Evaluate the basis of ``fit`` at ``points`` (N, 3) model units.

    Returns Basis(values (N, k), gradients (N, k, 3) in model units or None): float64 from the
    numpy backend, float32 from OpenCL. ``device`` selects the OpenCL device (ignored by numpy).
    """
    chosen = resolve_backend(backend, device)
    if chosen == "opencl":
        from .opencl import compute_basis as opencl_basis

        return opencl_basis(points, fit, gradients=gradients, device=device)
    from .reference import compute_basis as reference_basis

    return reference_basis(points, fit, gradients=gradients)
