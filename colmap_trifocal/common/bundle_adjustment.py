"""pycolmap bundle adjustment options as this package uses them (one place for the knobs)."""

from __future__ import annotations

import pycolmap


def bundle_adjustment_options(
    *,
    refine_focal_length: bool = True,
    refine_principal_point: bool = True,
    refine_extra_params: bool = False,
    function_tolerance: float | None = None,
    gradient_tolerance: float | None = None,
    max_iterations: int | None = None,
    threads: int | None = None,
) -> pycolmap.BundleAdjustmentOptions:
    """Options for ``pycolmap.bundle_adjustment`` / ``create_default_bundle_adjuster``.

    Poses and points are always refined; the camera's focal length(s), principal point
    and extra (distortion) parameters as asked. Ceres' summary is not printed. The
    solver tolerances (relative, Ceres' meaning), iteration limit and thread count keep
    pycolmap's defaults where None.
    """
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_focal_length = refine_focal_length
    options.refine_principal_point = refine_principal_point
    options.refine_extra_params = refine_extra_params
    options.print_summary = False
    solver = options.ceres.solver_options
    if function_tolerance is not None:
        solver.function_tolerance = function_tolerance
    if gradient_tolerance is not None:
        solver.gradient_tolerance = gradient_tolerance
    if max_iterations is not None:
        solver.max_num_iterations = max_iterations
    if threads is not None:
        solver.num_threads = threads
    return options
