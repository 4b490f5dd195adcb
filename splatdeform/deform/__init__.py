"""Everything in model units below the config layer: regions as masks, boundary rings, the
metaphors (handle, curve) behind one interface, the one fit and one basis per edit, and apply
(positions, normals, axes, 3DGS covariances and SH).

    masks + metaphors --layout--> rings --prepare--> Deformation --apply(delta_c)--> PointModel

Nothing here imports the config models or knows about units (:mod:`splatdeform.edit` converts
the config once into the masks, transforms and control points these functions take).
Public names are loaded on first use so that importing a submodule stays cheap.
"""

from __future__ import annotations

from splatdeform.lazy import lazy_exports

_MODULES = {
    "deformation": ("Deformation", "prepare", "prepare_metaphors", "prepare_handle",
                    "prepare_handles", "delta_for", "fit_settings", "FitSettings", "basis_settings",
                    "constraint_errors", "constraint_error", "FitFn", "BasisFn"),
    "regions": ("Group", "Layout", "layout", "check_regions", "check_metaphor"),
    "model_apply": ("apply", "full_basis", "handle_matrices", "check_finite"),
    "metaphor": ("Metaphor", "handle_metaphor"),
    "curve": ("curve_metaphor",),
    "handle": ("AffineFrame", "compose_transform", "delta_for_transform", "apply_affine"),
    "arrays": ("deform_frame",),
    "normals": ("estimate_normals",),
    "thin": ("thin_rings", "thin_ring"),
}
_LAZY = {name: module for module, names in _MODULES.items() for name in names}


__getattr__ = lazy_exports(__name__, _LAZY)


__all__ = sorted(_LAZY)
