"""The bounds of every view option, defined once: the edit config's ``render``, the batch's
``render``, the command line (``--size``, ``--fov``, ``--zoom``, ``--roll``, ``--frames``,
``--azimuth``, ``--elevation``), camera files and :class:`~splatdeform.render.camera.View` read
them from here (issue 44: they had drifted apart, e.g. a camera file allowed a 4-pixel width).

Plain numbers only: importing this module loads nothing else.
"""

from __future__ import annotations

MIN_IMAGE, MAX_IMAGE = 16, 8192   # image (one panel) width/height in pixels
DEFAULT_SIZE = (1200, 600)        # deform --render / render: the whole image
MIN_FOV, MAX_FOV = 1.0, 179.0     # the vertical lens angle, degrees
DEFAULT_FOV = 35.0
MIN_ZOOM, MAX_ZOOM = 0.01, 100.0  # narrows the view about the target
MAX_ROLL = 360.0                  # degrees about the view direction, either way
MAX_ANGLE = 1e6                   # azimuth / elevation, degrees (larger: a typo, not a view)
MAX_FRAMES = 1000                 # render.frames and --frames


def fov_line(value: object) -> str:
    """The one wording of a field-of-view refusal."""
    return f"expected degrees between {MIN_FOV:g} and {MAX_FOV:g}, got {value!r}"


def size_line(value: object) -> str:
    """The one wording of an image-size refusal."""
    return f"expected WIDTHxHEIGHT between {MIN_IMAGE} and {MAX_IMAGE}, got {value!r}"
