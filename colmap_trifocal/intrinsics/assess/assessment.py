"""The assessment stage: std, what is determined, where each value comes from, and why.

Turns one camera's final solve into its :class:`.results.CameraCalibration`. A
parameter is determined when it was estimated, its std is within tolerance (held
values' uncertainty counted) and the data actually moved it
(:func:`intrinsics.solve.constraints.data_moves`). Intrinsics and std in pixels.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from ...database.cameras import PINHOLE_MODELS
from ...geometry.tensor_estimation import TripletTensor
from ..inputs.camera_input import CameraInput
from ..lens.distortion import LensDistortion
from ..polish.stage import Polished
from ..results import (
    PARAMETER_NAMES,
    CameraCalibration,
    Diagnostics,
    Provenance,
    TripletReport,
    finite_or_none,
)
from ..solve.constraints import ConstraintSolution
from ..solve.fallback import FallbackSolution
from ..solve.parametrization import FreeParameters
from ..solve.theta import focal_scale, fold_focal_sign, theta_to_intrinsics
from ..start.candidates import StartCandidate
from ..start.focal_search import FocalSearchResult
from .diagnosis import diagnose

_SOURCE_WORDS = {"prior": "the prior", "focal-search": "the focal search's estimate"}


@dataclass(frozen=True)
class AssessInput:
    """What the assessment reads: the camera's final attempt and what followed it.

    Attributes:
        data: the camera's input (prior, stored camera).
        method: the trifocal variant.
        candidate: the start whose solve was kept (its held values).
        start: the normalisation of ``tensors`` (after a restart), pixels.
        tensors: the kept solve's tensors.
        fallback: the kept solve.
        polished: the estimate after the polish stage.
        search: the focal search (None: not run).
        tracks: per triplet, its tracks (3, n, 2), pixels (for the diagnosis).
        lens: the distortion the triplets show (:mod:`intrinsics.lens.distortion`),
            None when it was not estimated.
        workers: threads for the diagnosis (None: one per core).
        finding: a cause the earlier stages found (the lens search's bent tracks),
            first in the diagnosis.
        warped: the estimate comes from the lens search's warped tracks (the lens
            route).
    """

    data: CameraInput
    method: str
    candidate: StartCandidate
    start: np.ndarray
    tensors: list[TripletTensor]
    fallback: FallbackSolution
    polished: Polished
    search: FocalSearchResult | None
    tracks: list[np.ndarray]
    lens: LensDistortion | None = None
    workers: int | None = None
    finding: str | None = None
    warped: bool = False


@dataclass
class _Reported:
    """The values the result reports (pixels) and how each is known."""

    estimate: np.ndarray
    std: dict[str, float | None]
    observable: dict[str, bool]
    estimated: dict[str, bool]
    source: dict[str, str]
    unconstrained: dict[str, float | None]
    distortion: list[float] | None
    lens: LensDistortion | None
    lens_note: str | None


def assess(given: AssessInput) -> CameraCalibration:
    """The camera's result (its ``timing`` empty: the pipeline, which times this stage
    too, gives it)."""
    camera, fallback = given.data.camera, given.fallback
    reported = _reported(given)
    return CameraCalibration(
        camera_id=camera.camera_id,
        model=camera.model,
        method=given.method,
        fx=float(reported.estimate[0]),
        fy=float(reported.estimate[1]),
        cx=float(reported.estimate[2]),
        cy=float(reported.estimate[3]),
        std=reported.std,
        observable=reported.observable,
        num_triplets=len(given.tensors),
        num_inlier_triplets=given.polished.agreeing,
        prior=tuple(map(float, given.data.prior)),  # type: ignore[arg-type]
        start=tuple(map(float, given.start)),  # type: ignore[arg-type]
        assumptions=[
            note.replace("the prior", _SOURCE_WORDS[given.candidate.held_source], 1)
            if note.startswith("fx, fy")
            else note
            for note in given.polished.free_parameters.assumptions()
        ],
        estimated=reported.estimated,
        source=reported.source,
        distortion=reported.distortion,
        unconstrained_std=reported.unconstrained,
        diagnostics=Diagnostics(
            focal_search=search_summary(given.search),
            diagnosis=_joined(
                given.finding,
                reported.lens_note,
                None
                if all(reported.observable.values())
                else diagnose(given.tracks, reported.estimate, given.workers),
            ),
            triplet_bundle=given.polished.summary,
            lens_distortion=None if reported.lens is None else reported.lens.summary(),
            triplets=triplet_reports(given.tensors, fallback.solution, given.start),
            tensors=given.tensors,
        ),
        provenance=Provenance(stored_camera=camera),
    )


def _reported(given: AssessInput) -> _Reported:
    """The reported values: the polished estimate with the lens judged, each std,
    what is determined and where each value comes from; held values keep their start's
    std (a held value is known as well as its evidence)."""
    camera, fallback, candidate = given.data.camera, given.fallback, given.candidate
    start, polished, lens = given.start, given.polished, given.lens
    free_parameters = polished.free_parameters
    scale = focal_scale(start)
    estimate, relative_std, distortion, lens_note = with_lens(
        polished.intrinsics, polished.relative_std, lens, camera.model, scale
    )
    estimated = free_parameters.estimated(single_focal=camera.single_focal)
    within = (relative_std < fallback.tolerances) & fallback.moved
    observable = {
        name: estimated[name] and bool(ok) for name, ok in zip(PARAMETER_NAMES, within, strict=True)
    }
    if camera.single_focal:
        # One focal length for both axes assumes square pixels: the estimate of each
        # axis's focal length is known no better than the sensor's aspect ratio.
        relative_std = relative_std.copy()
        relative_std[:2] = np.hypot(relative_std[:2], SQUARE_PIXELS_STD)
    std = relative_std * scale
    unconstrained = fallback.unconstrained.relative_std * scale
    source = parameter_sources(estimated, free_parameters, candidate.held_source)
    reported_std = {
        name: finite_or_none(s) if estimated[name] else None
        for name, s in zip(PARAMETER_NAMES, std, strict=True)
    }
    held_focal = focal_scale(candidate.held)
    for index, name in enumerate(PARAMETER_NAMES):
        if source[name] in ("focal-search", "prior"):
            # It stays held where the lens adjustment refined it with the rest of the
            # principal point (pycolmap refines both coordinates or neither).
            reported_std[name] = float(candidate.held_std[index] * held_focal[index])
            estimate[index] = polished.intrinsics[index]
    pinhole = camera.model in PINHOLE_MODELS
    if given.warped:
        through_lens = lens is None or lens.corner_bend(camera.width, camera.height) >= STRONG_BEND
    else:
        # A pinhole camera's bent tracks keep the rule whatever the bend: without a warp
        # the tracks did not show the lens, and the fit's tangential terms also take up
        # errors that are not a lens's (KITTI's rectified frames: p1, p2 at 3 and 28 std).
        through_lens = pinhole and lens is not None and lens.present
    rule = None
    if through_lens:
        rule = THROUGH_LENS
    elif source["cx"] == "prior" and source["cy"] == "prior":
        rule = AT_HELD_CENTRE
    if rule is not None:
        estimate = estimate.copy()
        fitted_focal = float(np.sqrt(estimate[0] * estimate[1]))
        prior = np.asarray(given.data.prior, float)
        start_std = candidate.held_std * focal_scale(prior)
        held, judged = held_where_indecisive(
            estimate,
            reported_std,
            source,
            prior,
            start_std,
            supported_by_a_fit(rule, lens, prior),
            tie_fy=camera.single_focal,
        )
        unconstrained = _held_through_lens(unconstrained, rule, judged)
        lens_note = _joined(lens_note, held)
        observable = {name: observable[name] and source[name] != "prior" for name in observable}
        estimated = {name: estimated[name] and source[name] != "prior" for name in estimated}
        reported_focal = float(np.sqrt(estimate[0] * estimate[1]))
        if lens is not None and distortion is not None and reported_focal != fitted_focal:
            # The same distortion in pixels at the held focal length.
            lens = at_focal_ratio(lens, reported_focal / fitted_focal)
            distortion = [float(v) for v in lens.distortion]
    if lens is not None and source["fx"] in ("focal-search", "prior"):
        focal_std = reported_std["fx"] or candidate.held_std[0] * held_focal[0]
        lens = with_held_focal(lens, float(focal_std / estimate[0]))
    return _Reported(
        estimate=estimate,
        std=reported_std,
        observable=observable,
        estimated=estimated,
        source=source,
        unconstrained={
            name: finite_or_none(s) for name, s in zip(PARAMETER_NAMES, unconstrained, strict=True)
        },
        distortion=distortion,
        lens=lens,
        lens_note=lens_note,
    )


def _held_through_lens(
    unconstrained: np.ndarray, rule: HoldRule, judged: dict[str, float]
) -> np.ndarray:
    """The unconstrained std (4,), pixels, with each value that ``rule`` held on the lens
    route at the std of its estimate through the lens (``judged``, by name, from
    :func:`held_where_indecisive`). That estimate, every parameter estimated, is what the
    images say of the value; the warped tensors' constraints, whose std ``unconstrained``
    holds, only chose its triplets."""
    if rule is not THROUGH_LENS or not judged:
        return unconstrained
    out = unconstrained.copy()
    for name, value_std in judged.items():
        out[PARAMETER_NAMES.index(name)] = value_std
    return out


#: How far a sensor's pixels are from square, relative (fy / fx − 1): what a single focal
#: length leaves unknown of each axis's. 0.2 % is the RMS of the ground-truth fy / fx − 1
#: of the five real cameras in ``../shared/datasets`` (0.17, 0.30, 0.36, 0 and 0 %;
#: docs/uncertainty.md).
SQUARE_PIXELS_STD = 0.002


#: A value estimated through a strong lens (the lens route, or a pinhole camera's bent
#: tracks) replaces the start only where it is more than this many std from it.
DECISIVE_Z = 3.0
#: A lens counts as strong where it moves the farthest image corner by at least this
#: share of its distance from the principal point (:meth:`.LensDistortion.corner_bend`):
#: only there does an estimate through it rest on a warp and a fit that carry more error
#: than their std (``DECISIVE_Z``). EuRoC's drone lens bends it by a quarter (inf by its
#: one-term fit, which folds before the corner); real images through phone-like lenses
#: (k1 −0.1 to +0.05 at 3072×2048) by 0.7–4.5 %, and there the estimates through the lens
#: stand: 0.07–0.27 % off, ±2 std covering 156 of 160 errors (docs/lenses.md).
STRONG_BEND = 0.1
#: A focal length estimated while the principal point is held at the start replaces the
#: start only where it is more than this many std from it.
HELD_CENTRE_Z = 1.0


@dataclass(frozen=True)
class HoldRule:
    """Which estimated values stay at the start: those of ``names`` within ``z`` std of
    it; ``what`` names the estimate in the note."""

    z: float
    names: tuple[str, ...]
    what: str


THROUGH_LENS = HoldRule(DECISIVE_Z, PARAMETER_NAMES, "the estimate through the lens")
AT_HELD_CENTRE = HoldRule(HELD_CENTRE_Z, ("fx", "fy"), "the focal length at a held principal point")


def held_where_indecisive(
    estimate: np.ndarray,
    std: dict[str, float | None],
    source: dict[str, str],
    start: np.ndarray,
    start_std: np.ndarray,
    rule: HoldRule,
    *,
    tie_fy: bool = False,
) -> tuple[str | None, dict[str, float]]:
    """Hold at the start (in place) each estimated value that ``rule`` holds. A tied fy
    (``tie_fy``: a single-focal model) follows fx. ``start_std``: the start's std (4,),
    pixels. Returns the note naming the held values (None: none held) and, by name, the
    std of the estimate the rule judged for each value it held (a tied fy: fx's).

    Two estimates are held so:

    * One that rests on a strong lens (``DECISIVE_Z``): the lens search's warped
      tracks, or a pinhole camera's tracks bent by distortion it does not model.
    * A focal length estimated while the principal point is held at the start
      (``HELD_CENTRE_Z``): the images did not determine the principal point, so the
      focal length is fitted to the start's principal point, whose error biases it
      (the std counts that error), and a move within one std of the start is no
      evidence against the start (docs/accuracy.md, nineteenth session).

    Why for a strong lens: such an estimate rests on a warp and a distortion fit that
    carry more error than the std says; where it does not differ decisively from the
    start, the start is the better evidence. On EuRoC's drone lens from ±5 % priors the
    estimates land 3–9 % off, within 2 std of the start, and ended further from the
    truth than the start in 9 of 10 runs; on synthetic frames through k1 −0.2, k2 0.1 a
    SIMPLE_PINHOLE camera's tensors agree on f 38 % off with a std of 37 %.

    The held value's std is the start's, as for any held value, and at least reaches
    over the estimate's ±2 std interval (std + |estimate − start| / 2): the lens route's
    std of the principal point can be too small (EuRoC: cx 376.5 ± 1.6 px, truth 367.7).

    Where the std was widened to reach a second fit of the lens (the stored model's, where
    a richer model holds the lens: :attr:`.LensDistortion.fits`), its interval reaches as
    far beyond the reported fit as towards the other; a focal length's start beyond every
    fit's own ``rule.z`` std is supported by no model of the lens and is not held
    (:func:`supported_by_a_fit` leaves its name out of the rule's). On 7
    EuRoC frames in COLMAP's default camera (f 902 px, truth 459) the RADIAL fit gave
    477 ± 14 px and the SIMPLE_RADIAL one 663 ± 47: the widened std of 186 px held the
    start, 97 % off (docs/lenses.md).
    """
    start = np.asarray(start, float)
    held = []
    judged: dict[str, float] = {}
    for index, name in enumerate(PARAMETER_NAMES):
        value_std = std[name]
        if name not in rule.names or source[name] != "trifocal" or value_std is None:
            continue
        move = abs(float(estimate[index] - start[index]))
        if move > rule.z * value_std:
            continue
        held.append(f"{name} {estimate[index]:.1f} ± {value_std:.1f}")
        followers = [index]
        if name == "fx" and (tie_fy or source["fy"] == "tied"):
            followers.append(1)
        for follower in followers:
            judged[PARAMETER_NAMES[follower]] = value_std
            estimate[follower] = start[follower]
            std[PARAMETER_NAMES[follower]] = max(float(start_std[follower]), value_std + move / 2)
            source[PARAMETER_NAMES[follower]] = "prior"
    if not held:
        return None, judged
    note = f"held at the start where {rule.what} is within {rule.z:g} std of it ({', '.join(held)})"
    return note, judged


def supported_by_a_fit(rule: HoldRule, lens: LensDistortion | None, start: np.ndarray) -> HoldRule:
    """``rule`` holding a focal length only where its start lies between the lowest and
    the highest value within ``rule.z`` of some fit's own std
    (:attr:`.LensDistortion.fits`, pixels; a std that is not finite bounds nothing): a
    start beyond all of them is supported by no model of the lens. ``rule`` itself where
    the lens stage reported one fit.

    The focal length only: the fits differ in it because the stored model's f takes up
    the distortion it cannot hold, while their own std of the principal point is too
    small through a lens to bound anything (EuRoC's ten frames from the guess: cy 275 ± 11
    and 294 ± 9 px, truth 249, the start at the image centre, 240 px); it stays judged by
    the widened std alone.
    """
    if lens is None or not lens.fits:
        return rule
    values = np.array([values for values, _ in lens.fits], float)
    stds = np.array([std for _, std in lens.fits], float)
    reach = rule.z * np.where(np.isfinite(stds), stds, np.inf)
    start = np.asarray(start, float)
    supported = ((values - reach).min(axis=0) <= start) & (start <= (values + reach).max(axis=0))
    names = tuple(
        name
        for name, ok in zip(PARAMETER_NAMES, supported, strict=True)
        if name in rule.names and (ok or name in ("cx", "cy"))
    )
    return replace(rule, names=names)


def parameter_sources(
    estimated: dict[str, bool], free_parameters: FreeParameters, held_source: str
) -> dict[str, str]:
    """Where each reported value comes from: ``trifocal`` (estimated from the
    constraints), ``tied`` (fy = fx, square pixels assumed), ``focal-search`` or
    ``prior`` (held)."""
    source = {}
    for name in PARAMETER_NAMES:
        if estimated[name]:
            source[name] = "trifocal"
        elif name == "fy" and free_parameters.focal == "tied":
            source[name] = "tied"
        elif name in ("fx", "fy"):
            source[name] = held_source
        else:
            source[name] = "prior"
    return source


def search_summary(search: FocalSearchResult | None) -> dict[str, Any] | None:
    """The focal search's result for the JSON report (pixels; None if not run)."""
    if search is None:
        return None
    return {
        "focal": float(search.focal),
        "std": float(search.relative_std * search.focal),
        "decisive": bool(search.decisive),
        "used": bool(search.improves_on_start),
    }


def triplet_reports(
    tensors: list[TripletTensor], solution: ConstraintSolution, start: np.ndarray
) -> list[TripletReport]:
    """Per-tensor diagnostics of a solve (candidates and scores for msac / msac-opt)."""
    reports = []
    for index, tensor in enumerate(tensors):
        candidate = score = None
        if solution.per_tensor_theta is not None and solution.per_tensor_scores is not None:
            intrinsics = fold_focal_sign(
                theta_to_intrinsics(solution.per_tensor_theta[index], start)
            )
            candidate = tuple(map(float, intrinsics))
            score = float(solution.per_tensor_scores[index])
        reports.append(
            TripletReport(
                image_ids=tuple(int(i) for i in tensor.image_ids),  # type: ignore[arg-type]
                num_tracks=tensor.num_tracks,
                num_inliers=tensor.num_inliers,
                sigma_px=float(tensor.sigma_px),
                residual_norm=float(solution.norms[index]),
                inlier=bool(solution.inlier_tensors[index]),
                candidate=candidate,  # type: ignore[arg-type]
                score=score,
            )
        )
    return reports


def with_lens(
    intrinsics: np.ndarray,
    relative_std: np.ndarray,
    lens: LensDistortion | None,
    camera_model: str,
    focal_scale: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, list[float] | None, str | None]:
    """The estimate and its std (relative to the focal length) once the lens is judged.

    Without distortion in the tracks: unchanged. With it, a camera model that has
    distortion parameters takes the adjustment's K and distortion, with the larger of
    the adjustment's std and the estimate's (adding parameters to a fit cannot make
    the others better known); a pinhole camera (which stays pinhole) keeps its
    estimate, each std widened by how far the distortion moved that parameter (either
    focal length by the larger move of the two), and a note naming the cause.

    Returns:
        (fx, fy, cx, cy) in pixels, their std relative to the focal length, the
        distortion parameters to store (None: keep the stored ones), the note.
    """
    if lens is None or not lens.present:
        return intrinsics, relative_std, None, None
    words = ", ".join(
        f"{value:+.4f} ± {std:.4f}"
        for value, std in zip(lens.distortion, lens.distortion_std, strict=True)
    )
    if camera_model not in PINHOLE_MODELS:
        std = np.maximum(lens.intrinsics_std / focal_scale, relative_std)
        note = None
        if lens.misfit:
            note = (
                f"the {camera_model} camera cannot hold this lens's distortion (no "
                "triplet fits it as well as a projective camera): the estimate on the "
                "lens search's warped tracks and the warp's nearest k, each std "
                "widened to the model's closest camera; a model with more distortion "
                "terms (RADIAL, OPENCV) would fit it"
            )
        elif lens.richer_model is not None:
            note = (
                f"the {camera_model} camera cannot hold this lens's distortion (the "
                f"tracks determine {lens.richer_model}'s k2): K from the "
                f"{lens.richer_model} fit, k from the {camera_model} fit, each std "
                f"widened to the other fit; store the camera as {lens.richer_model} "
                "(or OPENCV)"
            )
        return lens.intrinsics.copy(), std, [float(v) for v in lens.distortion], note
    shift = np.abs(lens.intrinsics - intrinsics) / focal_scale
    # The fit trades its two focal lengths against the distortion (EuRoC, 8 frames: fx
    # 497, fy 527 px, truth 459 and 457): each axis is known no better than the larger move.
    shift[:2] = shift[:2].max()
    note = (
        f"radial distortion in the tracks (k {words}) that the {camera_model} camera "
        "does not model: the focal length is biased by it; store the camera as "
        "SIMPLE_RADIAL"
    )
    return intrinsics, np.hypot(relative_std, shift), None, note


#: How each distortion parameter scales with the focal length for the same distortion
#: in pixels (COLMAP's order: k1 with r², k2 with r⁴, OPENCV's p1, p2 with r).
_FOCAL_POWERS = {
    "SIMPLE_RADIAL": (2,),
    "RADIAL": (2, 4),
    "OPENCV": (2, 4, 1, 1),
}


def _focal_powers(model: str, count: int) -> np.ndarray:
    """The powers of f that ``model``'s first ``count`` distortion parameters scale with
    (``_FOCAL_POWERS``; 2 for a model not listed)."""
    return np.array(_FOCAL_POWERS.get(model, (2,) * count))[:count]


def at_focal_ratio(lens: LensDistortion, ratio: float) -> LensDistortion:
    """``lens`` with its distortion (and the richer model's) for a focal length ``ratio``
    times the fitted one: the same distortion in pixels at the same pixel radius (k1
    scales with f², k2 with f⁴, a tangential term with f)."""

    def scaled(values: np.ndarray, model: str) -> np.ndarray:
        return np.asarray(values, float) * ratio ** _focal_powers(model, len(values))

    richer = lens.richer_distortion
    return replace(
        lens,
        distortion=scaled(lens.distortion, lens.camera_model),
        richer_distortion=None
        if richer is None or lens.richer_model is None
        else scaled(richer, lens.richer_model),
    )


def with_held_focal(lens: LensDistortion, focal_std: float) -> LensDistortion:
    """``lens`` with each distortion std widened by what the held focal length's
    relative std ``focal_std`` does to it. The adjustment held f, so its std of k is
    conditional on f; the tracks fix the distortion in pixels, k1 = (distortion in
    pixels) · f² / r², so k1 moves by 2 · focal_std relative where f does (k2 by 4, a
    tangential term by 1)."""
    powers = _focal_powers(lens.camera_model, len(lens.distortion))
    spread = powers * np.abs(lens.distortion) * focal_std
    std = np.where(np.isfinite(lens.distortion_std), lens.distortion_std, 0.0)
    widened = np.hypot(std, spread)
    return replace(lens, distortion_std=np.where(np.isfinite(lens.distortion_std), widened, np.nan))


def _joined(*notes: str | None) -> str | None:
    """The notes that are given, joined with "; " (None when there are none)."""
    given = [note for note in notes if note]
    return "; ".join(given) if given else None
