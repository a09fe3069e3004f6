"""Normal integration: unit normals -> a height map (or, with intrinsics, a depth map).

Conventions. Normals are (H, W, 3) in the camera frame (x right, y up, z toward the camera);
image row 0 is the top. The surface is z = f(x, y) with x = column and y = -row in pixels, so
its unit normal is proportional to (-p, -q, 1) with p = dz/dx = -nx/nz and q = dz/dy = -ny/nz.
In array terms the targets are ``du = dz/dcol = -nx/nz`` and ``dv = dz/drow = +ny/nz`` (rows
run down while y runs up). ``nz`` is clipped to at least ``min_nz`` so grazing or backward
facing normals give bounded slopes (at most 1/min_nz px per px).

Perspective (``intrinsics`` = fx, fy, cx, cy in pixels): a pixel (u, v) = (col, row) sees the
point d * ((u - cx)/fx, (v - cy)/fy, 1) in the OpenCV frame (y down, z forward), where d is the
depth along the optical axis. Writing the normal in that frame, m = (nx, -ny, -nz), and
D = m . ((u - cx)/fx, (v - cy)/fy, 1), tangency of the surface gives the log-depth gradients
    d log(d)/du = -mx / (fx D),    d log(d)/dv = -my / (fy D),
so the same integrators solve for log-depth (scale-free), the perspective formulation surveyed
by Queau, Durou & Aujol ("Normal integration: a survey", JMIV 60, 2018) and used by BiNI.
D < 0 on visible surfaces; it is clipped to at most -min_nz.

Methods
- ``fc``: Frankot & Chellappa (IEEE TPAMI 10(4), 1988): project the gradient field on the
  integrable fields with the FFT. Full frame, gradients zero outside the mask; the field is first
  mirrored into a 2H x 2W periodic one (even extension of the height) so the frame border does
  not wrap around. Fast, but it cannot see the mask: heights leak across object borders.
- ``poisson``: least squares over mask pixels only. Every pixel contributes one-sided (forward
  and backward) difference equations along columns and rows, each weighted by the pixel's
  confidence (nz, or |D|): residual conf * ((z[next] - z[this]) - target). Each pixel's two
  sides share weight 1 (0.5 each; 1 for the only side at a border). The normal equations form a
  weighted graph Laplacian over the 4-neighbour mask graph (Neumann at the mask border),
  assembled with scipy.sparse and solved by conjugate gradients preconditioned with a
  smoothed-aggregation multigrid V-cycle (:class:`Multigrid`; 10-20 iterations, faster
  than a sparse LU on large masks: docs/benchmark.md). No equation crosses the mask border,
  so separate objects never pull on each other. The confidence makes grazing normals (whose
  slopes are the least reliable) count little: a steep feature one pixel wide is outvoted by
  its flat neighbours.
- ``bini``: discontinuity-aware, after the idea of bilateral normal integration (X. Cao,
  H. Santo, B. Shi, F. Okura, Y. Matsushita, "Bilateral Normal Integration", ECCV 2022): the
  same one-sided equations, but the share of each side is re-estimated from the current surface,
  w_forward = sigmoid(k * (back_diff^2 - forward_diff^2)), w_backward = 1 - w_forward, so at a
  depth jump the side that crosses it fades out and the step stays sharp; then solve again
  (iteratively reweighted least squares, starting from the ``poisson`` solution). Each re-solve
  runs a few conjugate-gradient steps preconditioned by the last multigrid hierarchy,
  rebuilding it only when the weights have drifted too far; the final surface is solved to
  CG_RTOL.

Output: height (H, W) float32 in pixel units, z toward the camera, NaN outside the valid mask.
The constant of integration is unknown; each 4-connected component is shifted so its lowest
point is 0. With intrinsics, depth (H, W) float32 is returned as well: the scale is unknown, so
each component's median depth is set to ``depth_ref`` (default fx, which makes one unit one
pixel at that distance), and height = (the component's largest depth) - depth.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import cv2
import numpy as np

from msfnet.common.camera import Intrinsics
from msfnet.common.errors import InputError
from msfnet.runtime.results.maps.extent import mask_box
from msfnet.runtime.results.maps.validate import check_normals

if TYPE_CHECKING:
    import scipy.sparse as sp

# SciPy is imported by the functions that solve (~0.4 s): importing msfnet (MapOptions, the
# constants here) must stay quick on an edge box that may never integrate a height map.

METHODS = ("fc", "poisson", "bini")
DEFAULT_MIN_NZ = 0.05
CG_RTOL = 1e-8  # relative residual of the final solves; heights then agree to ~1e-6 px
SOLVE_ITER = 100  # CG steps allowed for a full solve (multigrid needs ~10 on a Poisson system)
# a solve still above PROBE_RESIDUAL after PROBE_ITER steps retries with 2 x 2 aggregates
PROBE_ITER = 20
PROBE_RESIDUAL = 1e-3
INNER_ITER = 6  # CG steps per reweighting round (inexact: the weights move on anyway)
REBUILD_RESIDUAL = 1e-2  # an inner solve left above this: rebuild the multigrid hierarchy
COARSE_SIZE = 400  # unknowns on the coarsest multigrid level, solved by SuperLU
# side of the square blocks multigrid aggregates: 3 x 3 keeps coarse stencils narrow, 2 x 2
# widened them and slowed the setup on large parts (docs/benchmark.md)
AGGREGATE = 3
KEEP_PIXELS = 1 << 20  # graph and hierarchy kept for the next part with the same mask, to 1 MP
STRENGTH = 0.08
RIDGE = 1e-10  # relative diagonal ridge of the normal equations (see _system)
# damping of the Jacobi smoother and of the prolongator smoothing: 4 / (3 rho), rho the
# spectral radius of D^-1 A on that level (a fixed 2/3 diverged on deep Galerkin levels)
JACOBI_SCALE = 4.0 / 3.0
RADIUS_STEPS = 12  # power-iteration steps estimating rho on a Galerkin level
RADIUS_MARGIN = 1.1  # power iteration approaches rho from below
CROP_MARGIN = 8  # px of background kept around the object (fc's zero-gradient apron)


def components(valid: np.ndarray) -> tuple[int, np.ndarray]:
    """The mask's 4-connected components: their count and an (H, W) label image (0 outside,
    1..count in raster order of first pixel). OpenCV's, not SciPy's: ndimage costs a fresh
    process 0.06 s to import."""
    if valid.size == 0:  # OpenCV refuses an empty image
        return 0, np.zeros(valid.shape, np.int32)
    count, labels = cv2.connectedComponents(valid.astype(np.uint8), connectivity=4)
    return int(count) - 1, labels


@dataclass(frozen=True)
class Gradients:
    """Integration targets on the pixel grid (float64, zeros outside ``valid``).

    du: (H, W) target d(z)/d(column); dv: (H, W) target d(z)/d(row); z is height in pixels
        (orthographic) or natural log of depth (perspective).
    confidence: (H, W) per-pixel equation weight (clipped nz, or clipped |D|), 0 outside.
    valid: (H, W) bool, mask pixels with a usable normal.
    """

    du: np.ndarray
    dv: np.ndarray
    confidence: np.ndarray
    valid: np.ndarray


@dataclass
class Integration:
    """Result of :func:`integrate_normals`.

    height: (H, W) float32, pixel units (orthographic) or ``depth_ref`` units (perspective), z
        toward the camera, each component's minimum at 0, NaN outside the valid mask.
    depth: (H, W) float32 depth along the optical axis (perspective only, else None).
    method: "fc" | "poisson" | "bini"; iterations: reweighting rounds (1 for fc/poisson);
    builds: multigrid hierarchies built (0 for fc); seconds: wall time.
    """

    height: np.ndarray
    depth: np.ndarray | None
    method: str
    iterations: int = 1
    builds: int = 0
    seconds: float = 0.0


def target_gradients(
    normals: np.ndarray,
    mask: np.ndarray,
    intrinsics: Intrinsics | None = None,
    min_nz: float = DEFAULT_MIN_NZ,
) -> Gradients:
    """Per-pixel gradient targets from (H, W, 3) unit normals; see the module docstring."""
    n, valid = check_normals(normals, mask)
    if not 0 < min_nz <= 1:
        raise InputError(f"min_nz must lie in (0, 1], got {min_nz}")
    nx, ny, nz = n[..., 0], n[..., 1], n[..., 2]
    if intrinsics is None:
        c = np.maximum(nz, min_nz)
        du, dv = -nx / c, ny / c
    else:
        h, w = valid.shape
        rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
        mx, my, mz = nx, -ny, -nz  # the OpenCV camera frame: y down, z forward
        fx, fy, cx, cy = intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy
        d = np.minimum(mx * (cols - cx) / fx + my * (rows - cy) / fy + mz, -min_nz)
        du, dv = -mx / (fx * d), -my / (fy * d)
        c = -d
    zero = np.zeros_like(du)
    return Gradients(
        np.where(valid, du, zero), np.where(valid, dv, zero), np.where(valid, c, zero), valid
    )


# ----------------------------------------------------------------------------- Frankot-Chellappa


def frankot_chellappa(grad: Gradients) -> np.ndarray:
    """(H, W) float64 surface (height or log-depth) whose gradient is closest to the targets in
    the L2 sense over the whole frame, via the FFT of the even (mirrored) extension."""
    h, w = grad.du.shape
    # Even extension of z: du is odd across vertical mirrors, even across horizontal ones.
    du = np.concatenate([grad.du, -grad.du[:, ::-1]], axis=1)
    du = np.concatenate([du, du[::-1]], axis=0)
    dv = np.concatenate([grad.dv, grad.dv[:, ::-1]], axis=1)
    dv = np.concatenate([dv, -dv[::-1]], axis=0)
    wu = 2 * np.pi * np.fft.rfftfreq(2 * w)[None, :]
    wv = 2 * np.pi * np.fft.fftfreq(2 * h)[:, None]
    denom = wu**2 + wv**2
    denom[0, 0] = 1.0
    zf = (-1j * wu * np.fft.rfft2(du) - 1j * wv * np.fft.rfft2(dv)) / denom
    zf[0, 0] = 0.0
    return np.fft.irfft2(zf, s=(2 * h, 2 * w))[:h, :w]


# ----------------------------------------------------------------------------- least squares


@dataclass
class _Graph:
    """The 4-neighbour graph over valid pixels: index grid, edges, incidence, components."""

    index: np.ndarray  # (H, W) int64, -1 outside
    pixels: int
    h_edges: np.ndarray  # (H, W-1) bool: (r, c)-(r, c+1) both valid
    v_edges: np.ndarray  # (H-1, W) bool: (r, c)-(r+1, c) both valid
    incidence: sp.csr_matrix  # (E, P): +1 at the edge's second pixel, -1 at its first
    pins: np.ndarray  # one pixel index per connected component


def _graph(valid: np.ndarray) -> _Graph:
    import scipy.sparse as sp

    index = np.full(valid.shape, -1, np.int64)
    p = int(valid.sum())
    index[valid] = np.arange(p)
    he = valid[:, :-1] & valid[:, 1:]
    ve = valid[:-1] & valid[1:]
    first = np.concatenate([index[:, :-1][he], index[:-1][ve]])
    second = np.concatenate([index[:, 1:][he], index[1:][ve]])
    e = first.size
    rows = np.concatenate([np.arange(e), np.arange(e)])
    inc = sp.csr_matrix(
        (np.concatenate([-np.ones(e), np.ones(e)]), (rows, np.concatenate([first, second]))),
        shape=(e, p),
    )
    _, labels = components(valid)
    _, pins = np.unique(labels[valid], return_index=True)
    return _Graph(index, p, he, ve, inc, pins)


def _side_weights(
    z: np.ndarray | None, valid: np.ndarray, k: float, scale: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Shares of the forward/backward equations along columns and rows, each (H, W).

    With ``z`` None both sides get 0.5 (plain least squares); otherwise the BiNI rule
    w_forward = sigmoid(k * (back^2 - forward^2)) on differences of ``scale * z``. A pixel with
    only one side gives that side the whole weight.
    """
    from scipy.special import expit

    out = []
    for axis in (1, 0):
        # lo/hi: the first and second pixel of each neighbour pair along this axis
        lo: tuple[slice, slice] = (slice(None), slice(None, -1))
        hi: tuple[slice, slice] = (slice(None), slice(1, None))
        if axis == 0:
            lo, hi = lo[::-1], hi[::-1]  # type: ignore[assignment]
        pair = valid[lo] & valid[hi]
        has_f, has_b = np.zeros_like(valid), np.zeros_like(valid)
        has_f[lo] = pair
        has_b[hi] = pair
        both = has_f & has_b
        if z is None:
            wf = np.where(both, 0.5, 1.0)
        else:
            step = (z[hi] - z[lo]) * scale  # NaN where an end is outside the mask
            fwd, back = np.full(valid.shape, np.nan), np.full(valid.shape, np.nan)
            fwd[lo] = step
            back[hi] = step
            with np.errstate(invalid="ignore"):
                wf = np.where(both, expit(k * (back**2 - fwd**2)), 1.0)
        wb = np.where(both, 1.0 - wf, 1.0)
        out += [wf, wb]
    return out[0], out[1], out[2], out[3]


def _edge_terms(
    grad: Gradients, g: _Graph, wfu: np.ndarray, wbu: np.ndarray, wfv: np.ndarray, wbv: np.ndarray
) -> tuple[np.ndarray, ...]:
    """Per edge: weights (alpha, beta) of the two one-sided equations on it and their targets."""
    c2 = grad.confidence**2
    he, ve = g.h_edges, g.v_edges
    alpha = np.concatenate([(wfu * c2)[:, :-1][he], (wfv * c2)[:-1][ve]])
    beta = np.concatenate([(wbu * c2)[:, 1:][he], (wbv * c2)[1:][ve]])
    t_a = np.concatenate([grad.du[:, :-1][he], grad.dv[:-1][ve]])
    t_b = np.concatenate([grad.du[:, 1:][he], grad.dv[1:][ve]])
    return alpha, beta, t_a, t_b


def _system(
    g: _Graph, alpha: np.ndarray, beta: np.ndarray, t_a: np.ndarray, t_b: np.ndarray
) -> tuple[sp.csr_matrix, np.ndarray]:
    """Normal equations L z = b of sum_e alpha (dz_e - t_a)^2 + beta (dz_e - t_b)^2, with one
    pixel per component pinned (its diagonal raised) so L is positive definite."""
    import scipy.sparse as sp

    a = alpha + beta
    lap = (g.incidence.T @ sp.diags(a) @ g.incidence).tocsr()
    b = g.incidence.T @ (alpha * t_a + beta * t_b)
    scale = max(float(a.mean()) if a.size else 1.0, 1e-12)
    # A faint ridge on the whole diagonal keeps the system (and every multigrid level) positive
    # definite where the reweighting cuts a region loose from its pinned pixel; it moves heights
    # by ~1e-6 of their range.
    diag = np.full(g.pixels, RIDGE * scale)
    diag[g.pins] += scale
    return (lap + sp.diags(diag)).tocsr(), b


class Multigrid:
    """Smoothed-aggregation algebraic multigrid (after Vanek, Mandel & Brezina, Computing 56,
    1996) for the masked, weighted grid Laplacians above, used as a CG preconditioner.

    Aggregates come from geometry: the unknowns of each ``aggregate`` x ``aggregate`` block of
    the level's grid (pixels on the finest level; a coarse unknown sits at its block's place
    on the grid one level coarser), split into the pieces the level's operator connects
    inside the block. A block holding parts of two separate lines of the mask thus gives two
    aggregates, not one that ties unrelated heights together. The tentative prolongator maps
    each aggregate to its unknowns with weight 1 (it reproduces constants, the Laplacian's
    near-null space) and is smoothed by one damped Jacobi step. Coarse operators are Galerkin
    products P^T A P, down to ``coarse_size`` unknowns, which SuperLU factorises. ``solve(r)``
    applies one symmetric V-cycle (two damped Jacobi sweeps before and after), an approximation
    of A^-1 r. Every level's Jacobi damping is 4 / (3 rho) with rho its own spectral radius
    (:func:`_jacobi_radius`).
    """

    def __init__(
        self,
        mat: sp.csr_matrix,
        index: np.ndarray,
        coarse_size: int = COARSE_SIZE,
        aggregate: int | None = None,
        strength: float = STRENGTH,
    ) -> None:
        import scipy.sparse as sp

        side = AGGREGATE if aggregate is None else aggregate
        self.index = index  # kept: _solve may rebuild the hierarchy with smaller blocks

        # per level: the operator, the prolongator, the damped Jacobi step (omega / diagonal)
        self.levels: list[tuple[sp.csr_matrix, sp.csr_matrix, np.ndarray]] = []
        a = mat.tocsr()
        rows, cols = np.nonzero(index >= 0)  # each unknown's place (row-major = its number)
        while a.shape[0] > coarse_size:
            n = a.shape[0]
            rows, cols = rows // side, cols // side  # its block's place
            count, owner = _aggregates(a, rows * (int(cols.max()) + 1) + cols, strength)
            if count >= n:  # nothing merged (isolated unknowns): stop coarsening
                break
            tentative = sp.csr_matrix((np.ones(n), (np.arange(n), owner)), shape=(n, count))
            dinv = 1.0 / a.diagonal()
            step = (JACOBI_SCALE / _jacobi_radius(a, dinv)) * dinv
            prolong = (tentative - sp.diags(step) @ (a @ tentative)).tocsr()
            self.levels.append((a, prolong, step))
            coarse_rows, coarse_cols = np.empty(count, np.int64), np.empty(count, np.int64)
            coarse_rows[owner], coarse_cols[owner] = rows, cols
            rows, cols = coarse_rows, coarse_cols
            a = (prolong.T @ a @ prolong).tocsr()
        self.coarse = _factorise(a)

    def solve(self, r: np.ndarray, level: int = 0) -> np.ndarray:
        if level == len(self.levels):
            return self.coarse.solve(r)
        a, prolong, step = self.levels[level]
        x = step * r
        x += step * (r - a @ x)
        x += prolong @ self.solve(prolong.T @ (r - a @ x), level + 1)
        x += step * (r - a @ x)
        x += step * (r - a @ x)
        return x


def _aggregates(
    a: sp.csr_matrix, block: np.ndarray, strength: float = STRENGTH
) -> tuple[int, np.ndarray]:
    """(count, owner): the unknowns of each block split into the pieces that ``a``'s strong
    couplings inside the block connect (|a_ij| >= strength sqrt(a_ii a_jj)); owner numbers
    each unknown's piece. Where strength alone would leave more than half the unknowns
    unmerged, any non-zero coupling counts: a level that coarsens too little only moves the
    work to a deeper one, or to a large coarsest LU."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = a.shape[0]
    row = np.repeat(np.arange(n), np.diff(a.indptr))
    col = a.indices
    linked = (block[row] == block[col]) & (row != col) & (a.data != 0)
    root = np.sqrt(np.abs(a.diagonal()))
    strong = linked & (np.abs(a.data) >= strength * root[row] * root[col])
    for keep in (strong, linked):
        inside = sp.csr_matrix(
            (np.ones(int(np.count_nonzero(keep)), np.int8), (row[keep], col[keep])), shape=(n, n)
        )
        count, owner = connected_components(inside, directed=False)
        if count <= n // 2:
            break
    return int(count), owner


def _jacobi_radius(a: sp.csr_matrix, dinv: np.ndarray) -> float:
    """rho(D^-1 A) of a symmetric positive (semi)definite ``a``, never much below it (the
    damping 4 / (3 rho) contracts only while omega x rho < 2). The row-sum bound where it is at
    most 2 (the finest level, a weighted Laplacian, and some coarse ones: a little over-damped
    there); else a 10 % margin over a short power iteration on S = D^-1/2 A D^-1/2, but at
    least 1 + max |s_ij| (a 2 x 2 principal block's top eigenvalue, a true lower bound the
    power iteration can miss), and at most the row-sum bound (far too large on Galerkin
    levels, whose stencils hold many small entries of both signs)."""
    bound = float(np.max(abs(a).sum(axis=1).A1 * dinv))
    if bound <= 2.0 + 1e-9:
        return bound
    root = np.sqrt(dinv)
    coo = a.tocoo()
    off = coo.row != coo.col
    pair = float(np.max(np.abs(coo.data[off]) * root[coo.row[off]] * root[coo.col[off]]))
    v = np.random.default_rng(0).standard_normal(a.shape[0])
    estimate = 0.0
    for _ in range(RADIUS_STEPS):
        v /= np.sqrt(_dot(v, v))
        w = root * (a @ (root * v))
        estimate = _dot(v, w)
        v = w
    if not np.isfinite(estimate):
        return bound
    return min(bound, max(RADIUS_MARGIN * estimate, 1.0 + pair))


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    # einsum runs in this thread: a threaded BLAS dot spins waiting for cores on a busy machine
    return float(np.einsum("i,i->", a, b))


def _pcg(
    mat: sp.csr_matrix, b: np.ndarray, x0: np.ndarray, precond: Any, rtol: float, max_iter: int
) -> tuple[np.ndarray, float]:
    """Preconditioned conjugate gradients from ``x0``; returns (x, relative residual)."""
    x = x0.copy()
    r = b - mat @ x
    norm_b = max(np.sqrt(_dot(b, b)), 1e-300)
    stop = (rtol * norm_b) ** 2
    rr = _dot(r, r)
    if rr > stop:
        zr = precond.solve(r)
        p = zr.copy()
        rz = _dot(r, zr)
        for _ in range(max_iter):
            ap = mat @ p
            step = rz / _dot(p, ap)
            x += step * p
            r -= step * ap
            rr = _dot(r, r)
            if rr <= stop:
                break
            zr = precond.solve(r)
            rz_new = _dot(r, zr)
            p = zr + (rz_new / rz) * p
            rz = rz_new
    return x, float(np.sqrt(rr)) / norm_b


def _solve(mat: sp.csr_matrix, b: np.ndarray, x0: np.ndarray, mg: Multigrid) -> np.ndarray:
    """Solve to CG_RTOL with multigrid-preconditioned CG. Should that stall, go on from where
    it stopped with a hierarchy of 2 x 2 aggregates (stronger where confidences change
    sharply, e.g. large regions of grazing normals: docs/benchmark.md); a solve far from done
    after PROBE_ITER steps retries at once. As a last resort, a sparse LU, slower but direct."""
    x, relres = _pcg(mat, b, x0, mg, CG_RTOL, PROBE_ITER)
    if relres <= 10 * CG_RTOL:
        return x
    if relres <= PROBE_RESIDUAL:  # on its way (a slow start: speckle, dots)
        x, relres = _pcg(mat, b, x, mg, CG_RTOL, SOLVE_ITER - PROBE_ITER)
        if relres <= 10 * CG_RTOL:
            return x
    if AGGREGATE > 2:
        smaller = Multigrid(mat, mg.index, aggregate=2, strength=0.0)
        x, relres = _pcg(mat, b, x, smaller, CG_RTOL, SOLVE_ITER)
        if relres <= 10 * CG_RTOL:
            return x
    return _factorise(mat).solve(b)


def _factorise(mat: sp.csr_matrix) -> Any:
    """Sparse LU of a symmetric positive definite system: an ordering for A + A^T and no
    pivoting off the diagonal, which such a system never needs."""
    import scipy.sparse.linalg as sla

    symmetric = {"SymmetricMode": True}
    return sla.splu(
        mat.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options=symmetric
    )


def _to_grid(values: np.ndarray, g: _Graph) -> np.ndarray:
    out = np.full(g.index.shape, np.nan)
    out[g.index >= 0] = values
    return out


class _Kept:
    """The last mask's graph and multigrid hierarchy (one entry, up to KEEP_PIXELS pixels).
    A hierarchy built for one part's weights preconditions the next part's system as well
    (the weights are the normals' confidences, alike on parts of one fixture): CG still
    solves each system to CG_RTOL, and ``_solve`` builds a fresh hierarchy should it stall."""

    lock = threading.Lock()
    mask: np.ndarray | None = None
    graph: _Graph | None = None
    hierarchy: Multigrid | None = None


def _kept_for(valid: np.ndarray) -> tuple[_Graph, Multigrid | None]:
    """The kept graph and hierarchy when ``valid`` is the kept mask, else a new graph."""
    with _Kept.lock:
        held, graph, hierarchy = _Kept.mask, _Kept.graph, _Kept.hierarchy
    if held is not None and held.shape == valid.shape and np.array_equal(held, valid):
        assert graph is not None
        return graph, hierarchy
    return _graph(valid), None


def _keep(valid: np.ndarray, graph: _Graph, hierarchy: Multigrid) -> None:
    # bounded by the mask's bounding box too: the index and edge maps are the box's size
    if graph.pixels <= KEEP_PIXELS and graph.index.size <= 4 * KEEP_PIXELS:
        with _Kept.lock:
            _Kept.mask, _Kept.graph, _Kept.hierarchy = valid.copy(), graph, hierarchy


def least_squares_surface(
    grad: Gradients,
    *,
    discontinuities: bool = False,
    k: float = 2.0,
    scale: float = 1.0,
    max_iter: int = 50,
    tol: float = 1e-4,
) -> tuple[np.ndarray, int, int]:
    """Masked least-squares integration (``poisson``), or its BiNI-style reweighted form.

    Returns (z (H, W) float64 with NaN outside the valid mask, iterations, multigrid builds).
    ``k``: sharpness of the side weights (per squared unit of ``scale * z``; heights are in
    pixels, so k = 2 treats a jump of a pixel or more as a discontinuity). ``max_iter`` and
    ``tol`` (relative change of the energy) stop the reweighting.
    """
    g, mg = _kept_for(grad.valid)
    if g.pixels == 0:
        return np.full(grad.valid.shape, np.nan), 0, 0
    weights = _side_weights(None, grad.valid, k, scale)
    alpha, beta, t_a, t_b = _edge_terms(grad, g, *weights)
    mat, b = _system(g, alpha, beta, t_a, t_b)
    builds, iterations = 0, 1
    z = np.zeros_like(b)
    if mg is not None and not discontinuities:
        # the kept hierarchy, built for an earlier part: if it does not bring this system
        # to the tolerance within the probe (an odd part kept, an atypical one now), this
        # system gets its own, kept in its place
        z, relres = _pcg(mat, b, z, mg, CG_RTOL, PROBE_ITER)
        if relres <= 10 * CG_RTOL:
            return _to_grid(z, g), iterations, builds
        mg = None
    if mg is None or discontinuities:
        mg = Multigrid(mat, g.index)
        builds = 1
        if not discontinuities:
            _keep(grad.valid, g, mg)
    z = _solve(mat, b, z, mg)
    if not discontinuities:
        return _to_grid(z, g), iterations, builds

    def energy(zv: np.ndarray, al: np.ndarray, be: np.ndarray) -> float:
        dz = g.incidence @ zv
        return _dot(al, (dz - t_a) ** 2) + _dot(be, (dz - t_b) ** 2)

    e_old = energy(z, alpha, beta)
    for _ in range(max_iter - 1):
        weights = _side_weights(_to_grid(z, g), grad.valid, k, scale)
        alpha, beta, t_a, t_b = _edge_terms(grad, g, *weights)
        mat, b = _system(g, alpha, beta, t_a, t_b)
        # Inexact inner solve: the weights change again next round anyway. A few CG steps
        # preconditioned by the last multigrid hierarchy usually suffice; when they do not, the
        # weights have moved far from it and a fresh hierarchy pays for itself.
        z_new, relres = _pcg(mat, b, z, mg, CG_RTOL, INNER_ITER)
        if relres > REBUILD_RESIDUAL:
            mg = Multigrid(mat, g.index)
            builds += 1
            z_new, relres = _pcg(mat, b, z_new, mg, REBUILD_RESIDUAL * 1e-2, INNER_ITER)
        z = z_new
        iterations += 1
        e_new = energy(z, alpha, beta)
        if abs(e_old - e_new) <= tol * max(e_old, 1e-300):
            break
        e_old = e_new
    # polish: the returned surface solves the last weighted system to CG_RTOL
    z = _solve(mat, b, z, mg)
    return _to_grid(z, g), iterations, builds


# ----------------------------------------------------------------------------- entry point


F32 = np.finfo(np.float32)


def _check_depth(depth: np.ndarray, intrinsics: Intrinsics, depth_ref: float | None) -> None:
    """Refuse a part whose depths float32 cannot hold (silent inf / 0 depths and NaN heights
    otherwise), naming the likely cause: normals and intrinsics that fit no camera, or a
    depth_ref out of float32's range."""
    if np.isfinite(depth).all() and depth.max() < F32.max and depth.min() > F32.tiny:
        return
    if depth_ref is not None and not float(F32.tiny) < depth_ref < float(F32.max):
        raise InputError(f"depth_ref {depth_ref:g}: outside float32's range, which depths use")
    raise InputError(
        f"perspective depth: these normals with intrinsics fx {intrinsics.fx:g}, fy "
        f"{intrinsics.fy:g} give one part depths past float32's range (a field of view near "
        "180 degrees); the intrinsics must be in pixels of the image as run (after any "
        "downscale or ROI)"
    )


def _anchor(
    z: np.ndarray, valid: np.ndarray, intrinsics: Intrinsics | None, depth_ref: float | None
) -> tuple[np.ndarray, np.ndarray | None]:
    """Fix the free constant per 4-connected component (see the module docstring), for every
    component at once: a speckled mask has tens of thousands."""
    count, labels = components(valid)
    height = np.full(valid.shape, np.nan)
    depth = None if intrinsics is None else np.full(valid.shape, np.nan)
    if count == 0:  # an empty mask: all NaN, not an error
        return height, depth
    lab = labels[valid]
    vals = z[valid].astype(np.float64)
    if intrinsics is None:
        low = np.full(count + 1, np.inf)
        np.minimum.at(low, lab, vals)
        height[valid] = vals - low[lab]
        return height, depth
    assert depth is not None
    ref = intrinsics.fx if depth_ref is None else depth_ref
    with np.errstate(over="ignore", under="ignore"):
        d = ref * np.exp(vals - _medians(vals, lab, count)[lab])
    _check_depth(d, intrinsics, depth_ref)
    far = np.full(count + 1, -np.inf)
    np.maximum.at(far, lab, d)
    depth[valid] = d
    height[valid] = far[lab] - d
    return height, depth


def _medians(values: np.ndarray, labels: np.ndarray, count: int) -> np.ndarray:
    """np.median of ``values`` per label 1..count (index 0 unused), all in one sort."""
    order = np.lexsort((values, labels))
    ranked = values[order]
    sizes = np.bincount(labels, minlength=count + 1)
    start = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    out = np.zeros(count + 1)
    have = sizes > 0
    lo = start[have] + (sizes[have] - 1) // 2
    hi = start[have] + sizes[have] // 2
    out[have] = 0.5 * (ranked[lo] + ranked[hi])
    return out


def integrate_normals(
    normals: np.ndarray,
    mask: np.ndarray,
    method: str = "poisson",
    *,
    intrinsics: Intrinsics | tuple[float, float, float, float] | None = None,
    depth_ref: float | None = None,
    min_nz: float = DEFAULT_MIN_NZ,
    k: float = 2.0,
    max_iter: int = 50,
    tol: float = 1e-4,
) -> Integration:
    """Integrate (H, W, 3) unit normals over an (H, W) bool mask into a height map.

    method: "fc" (Frankot-Chellappa, FFT), "poisson" (masked least squares) or "bini"
    (discontinuity-aware reweighted least squares); see the module docstring for all three.
    intrinsics: (fx, fy, cx, cy) in pixels for a perspective camera, None = orthographic.
    depth_ref: median depth of each component (perspective only; default fx).
    k, max_iter, tol: "bini" only (sharpness, reweighting rounds, relative energy change).
    An empty (valid) mask gives an all-NaN height; a lone pixel gets height 0.
    Raises InputError for an unknown method, bad shapes or NaN normals inside the mask.
    """
    if method not in METHODS:
        raise InputError(f"integration method {method!r}: expected one of {', '.join(METHODS)}")
    intr = Intrinsics.coerce(intrinsics)
    if depth_ref is not None and not (np.isfinite(depth_ref) and depth_ref > 0):
        raise InputError(f"depth_ref must be a positive number, got {depth_ref}")
    start = time.perf_counter()
    unit, valid = check_normals(normals, mask)
    # Work on the object's bounding box (plus a margin for fc): the solvers only ever look at
    # valid pixels, and a small object in a large frame then costs what its own size costs.
    box = mask_box(valid, CROP_MARGIN)
    rs, cs = box if box is not None else (slice(0, valid.shape[0]), slice(0, valid.shape[1]))
    if intr is not None:
        intr = Intrinsics(intr.fx, intr.fy, intr.cx - cs.start, intr.cy - rs.start)
    grad = target_gradients(unit[rs, cs], valid[rs, cs], intr, min_nz)
    iterations, builds = 1, 0
    if method == "fc":
        z = frankot_chellappa(grad)
    else:
        # BiNI's weights compare depth jumps in pixels: log-depth differences times the
        # reference depth (fx by default) are that, near the reference distance.
        scale = 1.0 if intr is None else (intr.fx if depth_ref is None else depth_ref)
        z, iterations, builds = least_squares_surface(
            grad, discontinuities=method == "bini", k=k, scale=scale, max_iter=max_iter, tol=tol
        )
    h_box, d_box = _anchor(z, grad.valid, intr, depth_ref)
    height = np.full(valid.shape, np.nan, np.float32)
    height[rs, cs] = h_box
    depth = None
    if d_box is not None:
        depth = np.full(valid.shape, np.nan, np.float32)
        depth[rs, cs] = d_box
    return Integration(height, depth, method, iterations, builds, time.perf_counter() - start)


__all__ = [
    "DEFAULT_MIN_NZ",
    "METHODS",
    "Gradients",
    "Integration",
    "Intrinsics",
    "frankot_chellappa",
    "integrate_normals",
    "least_squares_surface",
    "target_gradients",
]
