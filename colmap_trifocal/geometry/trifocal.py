"""Trifocal tensor algebra, vectorised over leading batch dimensions.

Conventions (Hartley & Zisserman, ch. 15):

* Cameras ``P1 = [I | 0]``, ``P2 = [A | a4]``, ``P3 = [B | b4]`` (3x4 each).
* A tensor is an array ``T[..., i, j, k]`` of shape ``(..., 3, 3, 3)`` whose
  *correlation slices* are ``T_i = T[..., i, :, :] = a_i b4ᵀ − a4 b_iᵀ``
  (``a_i``, ``b_i`` the i-th columns of A and B).
* Point–point–point incidence: ``[x']× (Σ_i x^i T_i) [x'']× = 0``; the
  point–line–line form used for estimation is ``l'_j l''_k Σ_i x^i T_i^{jk} = 0``.
* Calibrating a tensor measured in pixels with intrinsics K (3x3, upper
  triangular ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``) gives the tensor of the
  normalised cameras: ``T̂_i = Σ_j K[j, i] · K⁻¹ T_j K⁻ᵀ``, then scaled to unit
  Frobenius norm.
* The 15 quartic constraints (Martyushev 2017, as written in the TrifocalCalib
  paper) vanish exactly on calibrated tensors; they are homogeneous of degree 4,
  so their value depends on the tensor scale (we always use unit Frobenius norm)
  but not on its sign.
"""

from __future__ import annotations

import numpy as np

CYCLIC = ((0, 1, 2), (1, 2, 0), (2, 0, 1))
NUM_CONSTRAINTS = 15
#: Codimension of the calibrated-tensor variety inside projective tensors
#: (18 dof of a trifocal tensor minus 11 of three calibrated cameras up to scale):
#: the number of independent constraints at a regular point.
CONSTRAINT_RANK = 7


def tensor_from_cameras(P2: np.ndarray, P3: np.ndarray) -> np.ndarray:
    """Tensor of ``P1 = [I|0]``, P2, P3: ``T_i = a_i b4ᵀ − a4 b_iᵀ``.

    Args:
        P2, P3: camera matrices of shape (..., 3, 4).

    Returns:
        Tensor of shape (..., 3, 3, 3), not normalised.
    """
    A, a4 = P2[..., :, :3], P2[..., :, 3]
    B, b4 = P3[..., :, :3], P3[..., :, 3]
    return np.asarray(
        np.einsum("...ji,...k->...ijk", A, b4) - np.einsum("...j,...ki->...ijk", a4, B)
    )


def normalize_tensor(T: np.ndarray) -> np.ndarray:
    """Scale each tensor of shape (..., 3, 3, 3) to unit Frobenius norm."""
    norm = np.sqrt(np.einsum("...ijk,...ijk->...", T, T))
    return np.asarray(T / norm[..., None, None, None])


def _null_vector(M: np.ndarray) -> np.ndarray:
    """Unit right null vector (smallest singular vector) of each (..., m, n) matrix."""
    return np.linalg.svd(M)[2][..., -1, :]


def epipoles_from_tensor(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Epipoles e' (in view 2) and e'' (in view 3) of tensors (..., 3, 3, 3), unit norm.

    e' is orthogonal to the left null vectors of the three slices, e'' to the
    right null vectors (H&Z Algorithm 15.1).
    """
    left = _null_vector(np.swapaxes(T, -1, -2))  # u_i with u_iᵀ T_i = 0, shape (..., 3, 3)
    right = _null_vector(T)  # v_i with T_i v_i = 0
    return _null_vector(left), _null_vector(right)


def cameras_from_tensor(T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cameras P2, P3 (..., 3, 4) compatible with ``P1 = [I|0]`` (H&Z Algorithm 15.1)."""
    e2, e3 = epipoles_from_tensor(T)
    A = np.einsum("...ijk,...k->...ji", T, e3)  # column i = T_i e''
    TtE = np.einsum("...ijk,...j->...ki", T, e2)  # column i = T_iᵀ e'
    proj = np.einsum("...a,...b->...ab", e3, e3) - np.eye(3)
    B = proj @ TtE
    P2 = np.concatenate([A, e2[..., :, None]], axis=-1)
    P3 = np.concatenate([B, e3[..., :, None]], axis=-1)
    return P2, P3


def point_line_line_rows(x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """Rows of the linear system ``A · vec(T) = 0`` for point correspondences.

    Each correspondence gives four equations, from the horizontal and vertical
    lines through x' and x'' (``l = (1, 0, −x)``, ``(0, 1, −y)``).

    Args:
        x1, x2, x3: inhomogeneous points (..., n, 2) in views 1, 2, 3.

    Returns:
        Array (..., n, 4, 27); ``vec(T)`` is ``T.reshape(27)`` (index i*9 + j*3 + k).
    """
    ones = np.ones(x1.shape[:-1] + (1,))
    p1 = np.concatenate([x1, ones], axis=-1)
    lines2 = _axis_lines(x2)  # (..., n, 2, 3)
    lines3 = _axis_lines(x3)
    rows = np.einsum("...i,...aj,...bk->...abijk", p1, lines2, lines3)
    return np.asarray(rows.reshape(x1.shape[:-1] + (4, 27)))


def _axis_lines(x: np.ndarray) -> np.ndarray:
    """The vertical and horizontal lines (..., 2, 3) through inhomogeneous points (..., 2)."""
    lines = np.zeros(x.shape[:-1] + (2, 3))
    lines[..., 0, 0] = 1.0
    lines[..., 0, 2] = -x[..., 0]
    lines[..., 1, 1] = 1.0
    lines[..., 1, 2] = -x[..., 1]
    return lines


def linear_tensor(x1: np.ndarray, x2: np.ndarray, x3: np.ndarray) -> np.ndarray:
    """Least-squares linear tensor from n ≥ 7 correspondences (..., n, 2) per view.

    The caller normalises the coordinates (here: intrinsics-normalised points,
    which are centred and of unit scale). Batch dimensions are solved at once.
    The result satisfies no internal constraint; see :func:`cameras_from_tensor`
    for a geometrically valid tensor.
    """
    rows = point_line_line_rows(x1, x2, x3)
    system = rows.reshape(rows.shape[:-3] + (-1, 27))
    # full_matrices=False: U of a (4n x 27) system would be 4n x 4n otherwise.
    vt = np.linalg.svd(system, full_matrices=False)[2]
    return vt[..., -1, :].reshape(rows.shape[:-3] + (3, 3, 3))


def calibrate_tensor(T: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Tensor of normalised cameras: ``T̂_i = Σ_j K[j,i] K⁻¹ T_j K⁻ᵀ``, unit Frobenius norm.

    Args:
        T: tensors (..., 3, 3, 3) in the image coordinates that K maps to.
        K: intrinsics (..., 3, 3), upper triangular, broadcast against T's batch
            dimensions.
    """
    K_inv = upper_triangular_inverse(K)[..., None, :, :]
    inner = K_inv @ T @ np.swapaxes(K_inv, -1, -2)  # K⁻¹ T_j K⁻ᵀ, (..., 3, 3, 3)
    mixed = np.swapaxes(K, -1, -2) @ inner.reshape(inner.shape[:-3] + (3, 9))
    return normalize_tensor(mixed.reshape(mixed.shape[:-1] + (3, 3)))


def upper_triangular_inverse(K: np.ndarray) -> np.ndarray:
    """The inverse (..., 3, 3) of upper-triangular matrices K (..., 3, 3), in closed form
    (the solve calibrates thousands of tensors per run; a batched LU costs more than
    the calibration itself). A singular K (a zero on the diagonal) gives non-finite
    entries rather than an exception."""
    K = np.asarray(K, dtype=float)
    a, s, c = K[..., 0, 0], K[..., 0, 1], K[..., 0, 2]
    b, d, e = K[..., 1, 1], K[..., 1, 2], K[..., 2, 2]
    inverse = np.zeros(K.shape)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse[..., 0, 0] = 1.0 / a
        inverse[..., 0, 1] = -s / (a * b)
        inverse[..., 0, 2] = (s * d - c * b) / (a * b * e)
        inverse[..., 1, 1] = 1.0 / b
        inverse[..., 1, 2] = -d / (b * e)
        inverse[..., 2, 2] = 1.0 / e
    return inverse


def quartic_constraints(T: np.ndarray) -> np.ndarray:
    """The 15 quartic constraints of a calibrated trifocal tensor.

    With ``U_k = T_k T_kᵀ`` and ``V_k = T_k T_{k+1}ᵀ + T_{k+1} T_kᵀ`` (k cyclic) and
    ``ψ(X, Y) = tr X tr Y − 2 tr(XY)``: for each cyclic relabelling (1,2,3) → (a,b,c)
    of the slices,

    * ψ(U_c − U_a, U_c − U_a) − ψ(V_c, V_c)
    * ψ(U_c − U_a, V_a) + ψ(V_b, V_c)
    * ψ(U_a − U_b, V_a)
    * tr(U_b)² − tr(V_c)² − tr(U_b² − V_c² + (U_c − U_a)²)
    * tr(V_b) tr(U_a − 2U_b − U_c) − tr(V_a) tr(V_c) + 2 tr(V_b U_b)

    Every term is a product of traces or a ``tr(XY)``, which is bilinear, so all of
    them are one linear map (:data:`_TRACE_COEFFICIENTS`) of the products of the six
    traces of (U_1, U_2, U_3, V_1, V_2, V_3) and of their 6x6 table of ``tr(XY)``
    (``Σ X ∘ Y``: the U and V are symmetric). Every product ``T_k T_lᵀ`` of two slices
    comes from one 9x3 by 3x9 product.

    Args:
        T: tensors (..., 3, 3, 3), normally of unit Frobenius norm.

    Returns:
        Constraint values (..., 15); zero for calibrated tensors, in the order above
        (the first three for each relabelling, then the last two for each).
    """
    batch = T.shape[:-3]
    rows = T.reshape(batch + (9, 3))
    products = (rows @ np.swapaxes(rows, -1, -2)).reshape(batch + (3, 3, 3, 3))
    # Row 3k + l of ``blocks`` is T_k T_lᵀ, flattened.
    blocks = np.swapaxes(products, -3, -2).reshape(batch + (9, 9))
    M = _SLICE_PRODUCTS_TO_UV @ blocks  # rows U_1, U_2, U_3, V_1, V_2, V_3, flattened
    t = M[..., 0::4].sum(axis=-1)  # traces, (..., 6)
    G = M @ np.swapaxes(M, -1, -2)  # tr(M_i M_j), (..., 6, 6)
    features = np.concatenate([t[..., :, None] * t[..., None, :], G], axis=-1)
    return np.asarray(features.reshape(batch + (72,)) @ _TRACE_COEFFICIENTS)


def _constraints_from_traces(t: np.ndarray, G: np.ndarray) -> np.ndarray:
    """The 15 constraints (15,) of :func:`quartic_constraints` written out from the
    traces t (6,) and the table G (6, 6) of ``tr(M_i M_j)``; quadratic in t, linear
    in G."""
    traces_DD = [G[c, c] - 2.0 * G[c, a] + G[a, a] for a, _, c in CYCLIC]  # tr((U_c − U_a)²)
    values = []
    for (a, b, c), trace_DD in zip(CYCLIC, traces_DD, strict=True):
        va, vb, vc = 3 + a, 3 + b, 3 + c
        trace_D = t[c] - t[a]
        values.append(trace_D**2 - 2.0 * trace_DD - t[vc] ** 2 + 2.0 * G[vc, vc])
        values.append(
            trace_D * t[va] - 2.0 * (G[c, va] - G[a, va]) + t[vb] * t[vc] - 2.0 * G[vb, vc]
        )
        values.append((t[a] - t[b]) * t[va] - 2.0 * (G[a, va] - G[b, va]))
    for (a, b, c), trace_DD in zip(CYCLIC, traces_DD, strict=True):
        va, vb, vc = 3 + a, 3 + b, 3 + c
        values.append(t[b] ** 2 - t[vc] ** 2 - (G[b, b] - G[vc, vc] + trace_DD))
        values.append(t[vb] * (t[a] - 2.0 * t[b] - t[c]) - t[va] * t[vc] + 2.0 * G[vb, b])
    return np.array(values)


def _trace_coefficients() -> np.ndarray:
    """(72, 15): the constraints as a linear map of ``[t tᵀ | G]`` (6 rows of 12),
    flattened: G's part from unit tables, the quadratic form in t by polarisation
    (``½ (q(eᵢ + eⱼ) − q(eᵢ) − q(eⱼ))``, which is q(eᵢ) where i = j).
    Every coefficient is a small multiple of 1/2, exact in floating point."""
    unit, zero_t, zero_G = np.eye(6), np.zeros(6), np.zeros((6, 6))

    def quadratic(t: np.ndarray) -> np.ndarray:
        return _constraints_from_traces(t, zero_G)

    coefficients = np.zeros((6, 12, 15))
    for i in range(6):
        for j in range(6):
            coefficients[i, 6 + j] = _constraints_from_traces(zero_t, np.outer(unit[i], unit[j]))
            coefficients[i, j] = 0.5 * (
                quadratic(unit[i] + unit[j]) - quadratic(unit[i]) - quadratic(unit[j])
            )
    return coefficients.reshape(72, 15)


def _slice_products_to_uv() -> np.ndarray:
    """(6, 9): the slice products T_k T_lᵀ (row 3k + l) to U_k (k = l) and
    V_k = T_k T_{k+1}ᵀ + T_{k+1} T_kᵀ."""
    selection = np.zeros((6, 9))
    for k in range(3):
        following = (k + 1) % 3
        selection[k, 4 * k] = 1.0
        selection[3 + k, 3 * k + following] = 1.0
        selection[3 + k, 3 * following + k] = 1.0
    return selection


#: The constraints' coefficients on ``[t tᵀ | G]`` (:func:`_trace_coefficients`).
_TRACE_COEFFICIENTS = _trace_coefficients()
#: :func:`_slice_products_to_uv`.
_SLICE_PRODUCTS_TO_UV = _slice_products_to_uv()


def intrinsics_matrix(params: np.ndarray) -> np.ndarray:
    """K (..., 3, 3) from (..., 4) = (fx, fy, cx, cy)."""
    params = np.asarray(params, dtype=float)
    K = np.zeros(params.shape[:-1] + (3, 3))
    K[..., 0, 0] = params[..., 0]
    K[..., 1, 1] = params[..., 1]
    K[..., 0, 2] = params[..., 2]
    K[..., 1, 2] = params[..., 3]
    K[..., 2, 2] = 1.0
    return K
