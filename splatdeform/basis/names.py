"""The basis backend names, listed once (config, CLI and dispatcher use this tuple)."""

BACKENDS = ("auto", "numpy", "opencl")
