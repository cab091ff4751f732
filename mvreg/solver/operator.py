"""The data matrix C of O-REG (DESIGN.md section 2), dense or matrix-free.

Eliminating node positions z and translations t from REG leaves
``min Tr(C O^T O)`` with ``C = C0 - B S^+ B^T`` (Md x Md), where (with
``n_k = sum_i w_ki`` and ordered pairs (l, l') of observations of one node):

    C0[i,j] = delta_ij sum_{l in i} w_l (1 - w_l/n_k) x_l x_l^T - sum_pairs w_l w_l'/n_k x_l x_l'^T
    B[i,j]  = delta_ij sum_{l in i} w_l (1 - w_l/n_k) x_l       - sum_pairs w_l w_l'/n_k x_l
    S[i,j]  = delta_ij sum_{l in i} w_l (1 - w_l/n_k)           - sum_pairs w_l w_l'/n_k

S (M x M) is the weighted Laplacian of the patch graph; C0 and B are sparse with the
block pattern of the patch graph. Nothing of size (N+M)^2 is ever formed.

Data are centred per patch and scaled by one global factor first, so that rho and
tolerances do not depend on units; translations and nodes are mapped back.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from mvreg.solver import pardiso
from mvreg.solver.krylov import dense_factor, laplacian_pcg
from mvreg.solver.problem import PatchProblem

# Above this many patches the Laplacian is solved by preconditioned CG instead of a
# sparse LU (LU fill-in grows superlinearly on random overlap graphs).
DIRECT_LAPLACIAN_MAX_PATCHES = 20000
# With PARDISO a Laplacian whose factor is forecast nearly dense and costly
# (krylov.dense_factor) is solved by Jacobi-PCG instead (random overlap graph, M = 10k:
# factor 9e6 nonzeros, 3.7 s, 25-70 ms per solve; PCG 42 iterations to 1e-15, 4-20 ms).
# Iterative refinement of the factorized Laplacian solves: a step is taken only while the
# normwise backward error ||b - S x||_inf / (||S||_inf ||x||_inf + ||b||_inf) exceeds
# this (an LDL^T with pivoting is backward stable: ~1e-16 as a rule, and a refinement step
# in the same precision cannot do better). PARDISO's own refinement took both its steps on
# every solve: random graph, M = 1,000, 1.04 ms per 3-column solve against 0.27 ms.
REFINE_BACKWARD_ERROR = 1e-14
REFINE_MAX_STEPS = 2


class LaplacianSolver:
    """Solves S x = b for the patch-graph Laplacian S (gauge: x_0 = 0, then mean-free).

    MKL PARDISO (any size) when available, unless its analysis forecasts a nearly dense
    factor (an expander: no small separators, ``krylov.dense_factor``): then "pcg",
    Jacobi-preconditioned CG to the rounding floor, which converges in a few dozen steps
    exactly there (large spectral gap); should it not converge, S is factorized after all.
    Otherwise small graphs: sparse LU of S with patch 0 grounded; large graphs: CG with an
    algebraic-multigrid (smoothed aggregation) preconditioner, which stays linear in M,
    warm-started per right-hand-side block when the caller passes ``x0``.
    """

    def __init__(self, S: sp.csr_matrix, method: str = "auto", rtol: float = 1e-12):
        self.m = S.shape[0]
        self.rtol = rtol
        self.S = S.tocsr()
        self.red = self.S[1:, 1:].tocsc()
        if method == "auto":
            if pardiso.available():
                method = "pcg" if self._factor_fills_in() else "pardiso"
            else:
                method = "direct" if self.m <= DIRECT_LAPLACIAN_MAX_PATCHES else "amg-cg"
        self.method = method
        self.cg_iterations = 0
        if self.m == 1:
            return
        if method == "pardiso":
            self._lu = pardiso.PardisoFactor(self.red)
        elif method == "pcg":
            pass
        elif method == "direct":
            self._lu = spla.splu(self.red, permc_spec="MMD_AT_PLUS_A")
        elif method == "amg-cg":
            import pyamg

            self._ml = pyamg.smoothed_aggregation_solver(self.red.tocsr(), symmetry="symmetric")
            self._prec = self._ml.aspreconditioner(cycle="V")
        else:
            raise ValueError(f"unknown Laplacian method {method!r}")

    def solve(self, b: np.ndarray) -> np.ndarray:
        """b: (M,) or (M, r) with columns summing to ~0. Returns x with the same shape."""
        squeeze = b.ndim == 1
        b2 = b[:, None] if squeeze else b
        x = np.zeros_like(b2)
        if self.m > 1:
            if self.method == "pcg":
                x = self._pcg(b2)
            elif self.method in ("direct", "pardiso"):
                x[1:] = self._refined(np.ascontiguousarray(b2[1:]))
            else:
                for c in range(b2.shape[1]):
                    rhs = b2[1:, c]
                    nb = np.linalg.norm(rhs)
                    if nb == 0:
                        continue
                    sol, _ = spla.cg(
                        self.red, rhs, rtol=self.rtol, atol=0.0, M=self._prec, maxiter=500
                    )
                    x[1:, c] = sol
        x -= x.mean(axis=0, keepdims=True)
        return x[:, 0] if squeeze else x

    def _refined(self, b: np.ndarray) -> np.ndarray:
        """The factorized solve of the grounded system, refined while its backward error is
        above ``REFINE_BACKWARD_ERROR``."""
        x = self._lu.solve(b)
        if getattr(self, "_norm", None) is None:
            self._norm = float(abs(self.red).sum(axis=1).max())
        nb = float(np.max(np.abs(b))) if b.size else 0.0
        for _ in range(REFINE_MAX_STEPS):
            r = b - self.red @ x
            scale = self._norm * float(np.max(np.abs(x))) + nb
            if not float(np.max(np.abs(r))) > REFINE_BACKWARD_ERROR * scale:
                break
            x = x + self._lu.solve(r)
        return x

    def _factor_fills_in(self) -> bool:
        """PARDISO's forecast for the grounded Laplacian: a nearly dense, costly factor."""
        if self.m < 2:
            return False
        f = pardiso.PardisoFactor(self.red, analyse_only=True)
        self.forecast = {"factor_nnz": f.factor_nnz, "factor_flops": f.factor_flops}
        return dense_factor(f.factor_nnz, self.m - 1, f.factor_flops)

    def _pcg(self, b: np.ndarray) -> np.ndarray:
        """Jacobi-PCG on S; where it does not converge, factorize S and solve directly."""
        x, its, ok = laplacian_pcg(self.S, b)
        self.cg_iterations += its
        if ok:
            return x
        # The Krylov path failed here: factorize from now on.
        if pardiso.available():
            self.method, self._lu = "pardiso", pardiso.PardisoFactor(self.red)
        else:
            self.method, self._lu = "direct", spla.splu(self.red, permc_spec="MMD_AT_PLUS_A")
        x = np.zeros_like(b)
        x[1:] = self._refined(np.ascontiguousarray(b[1:]))
        return x


@dataclass
class Normalization:
    """Local coords were mapped as x' = (x - centroid[patch]) / scale."""

    centroids: np.ndarray  # (M, d)
    scale: float


class RegOperator:
    """C = C0 - B S^+ B^T for a PatchProblem, applied matrix-free or formed densely.

    Attributes:
        d, M: dimension and number of patches; n = M d.
        C0: (n, n) csr, B: (n, M) csr, S: (M, M) csr (normalized data).
        norm: the Normalization applied to the data.
        timings: seconds spent building (dict).
    """

    def __init__(self, problem: PatchProblem, laplacian: str = "auto"):
        t0 = time.perf_counter()
        self.problem = problem
        self.d, self.M = problem.d, problem.num_patches
        self.n = self.d * self.M
        self.norm = _normalization(problem)
        self.C0, self.B, self.S = _assemble(problem, self.norm)
        t1 = time.perf_counter()
        self.lap = LaplacianSolver(self.S, laplacian)
        self.num_matvecs = 0
        self._dense = None
        # PARDISO's forecast of the bordered system's factorization (shift_invert.py).
        self.factor_forecast: dict | None = None
        # Which paths the solver took where it chooses from the data (krylov.py): e.g.
        # "polish": "block-jacobi CG" or polish.STALLED; copied into SolveResult.stats.
        self.paths: dict = {}
        self.timings = {"assemble": t1 - t0, "laplacian_setup": time.perf_counter() - t1}

    # ------------------------------------------------------------------ products
    def matvec(self, v: np.ndarray) -> np.ndarray:
        """C v for v of shape (n,) or (n, r)."""
        if self._dense is not None:
            return self._dense @ v
        self.num_matvecs += 1 if v.ndim == 1 else v.shape[1]
        bt = self.B.T @ v
        return self.C0 @ v - self.B @ self.lap.solve(bt)

    def diagonal_blocks(self) -> np.ndarray:
        """(M, d, d) diagonal blocks of C0 (each patch's own second moments), cached: the
        block-Jacobi preconditioners of the iterative paths (spectral.py, polish.py)."""
        if getattr(self, "_blocks", None) is None:
            d, c0 = self.d, self.C0.tocoo()
            same = c0.row // d == c0.col // d
            b = np.zeros((self.M, d, d))
            np.add.at(b, (c0.row[same] // d, c0.row[same] % d, c0.col[same] % d), c0.data[same])
            self._blocks = b
        return self._blocks

    def as_linear_operator(self) -> spla.LinearOperator:
        return spla.LinearOperator(
            (self.n, self.n), matvec=self.matvec, matmat=self.matvec, dtype=np.float64
        )

    def dense(self) -> np.ndarray:
        """The dense (n, n) C. Costs O(n^2) memory: for moderate M only."""
        if self._dense is None:
            bt = self.B.T.toarray()  # (M, n)
            x = self.lap.solve(bt)
            c = self.C0.toarray() - self.B @ x
            self._dense = 0.5 * (c + c.T)
        return self._dense

    def objective(self, R: np.ndarray) -> float:
        """Tr(C O^T O) for rotations R (M, d, d), O = [R_1 .. R_M]; normalized units."""
        o_t = R.transpose(0, 2, 1).reshape(self.n, self.d)  # O^T (n, d)
        return float(np.sum(o_t * self.matvec(o_t)))

    # ------------------------------------------------------------------ translations
    def translations(self, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Optimal translations (M, d) and node positions (N, d) for rotations R.

        In the problem's own units and frame, before any gauge choice.
        """
        d, m = self.d, self.M
        o = R.transpose(1, 0, 2).reshape(d, m * d)  # O = [R_1 .. R_M], (d, n)
        ob = (self.B.T @ o.T).T  # (d, M) = O B
        t_norm = -self.lap.solve(ob.T).T  # (d, M): T S = -O B
        # Undo normalization: t_i = s t'_i - R_i c_i.
        s, c = self.norm.scale, self.norm.centroids
        t = s * t_norm.T - np.einsum("mij,mj->mi", R, c)
        return t, self.node_positions(R, t)

    def node_positions(self, R: np.ndarray, t: np.ndarray) -> np.ndarray:
        """z_k = weighted mean of R_i x_ki + t_i over the patches that see node k."""
        p = self.problem
        y = np.einsum("kij,kj->ki", R[p.patch], p.coords) + t[p.patch]
        w = np.where(p.weight > 0, p.weight, 0.0)
        nk = np.bincount(p.node_index, weights=w, minlength=p.num_nodes)
        z = np.stack(
            [
                np.bincount(p.node_index, weights=w * y[:, a], minlength=p.num_nodes)
                for a in range(p.d)
            ],
            1,
        )
        # Nodes seen only with zero weight: plain average, so they still get a position.
        zero = nk <= 0
        if np.any(zero):
            cnt = np.bincount(p.node_index, minlength=p.num_nodes)
            zu = np.stack(
                [
                    np.bincount(p.node_index, weights=y[:, a], minlength=p.num_nodes)
                    for a in range(p.d)
                ],
                1,
            )
            z[zero] = zu[zero] / cnt[zero, None]
            nk = np.where(zero, 1.0, nk)
        return z / nk[:, None]

    def residual(self, R: np.ndarray, t: np.ndarray, z: np.ndarray | None = None) -> float:
        """REG cost sum w ||z_k - R_i x_ki - t_i||^2 in the problem's units."""
        p = self.problem
        if z is None:
            z = self.node_positions(R, t)
        y = np.einsum("kij,kj->ki", R[p.patch], p.coords) + t[p.patch]
        return float(np.sum(p.weight * np.sum((z[p.node_index] - y) ** 2, axis=1)))


def _normalization(problem: PatchProblem) -> Normalization:
    p, x, w, m, d = problem.patch, problem.coords, problem.weight, problem.num_patches, problem.d
    ww = np.where(w > 0, w, 0.0)
    sw = np.bincount(p, weights=ww, minlength=m)
    cnt = np.bincount(p, minlength=m)
    cen = np.empty((m, d))
    for a in range(d):
        num = np.bincount(p, weights=ww * x[:, a], minlength=m)
        plain = np.bincount(p, weights=x[:, a], minlength=m) / cnt
        cen[:, a] = np.where(sw > 0, num / np.maximum(sw, 1e-300), plain)
    xc = x - cen[p]
    tot = ww.sum()
    scale = float(np.sqrt(np.sum(ww * np.sum(xc**2, axis=1)) / tot)) if tot > 0 else 1.0
    if not np.isfinite(scale) or scale <= 0:
        scale = 1.0
    return Normalization(centroids=cen, scale=scale)


def _assemble(problem: PatchProblem, norm: Normalization):
    """(C0, B, S) of the REG cost with the node positions eliminated, as sparse products.

    Node k's optimal position is the weighted mean of its observations, so the cost is
    sum_a w_a ||y_a||^2 - sum_k ||sum_a w_a y_a||^2 / n_k over observations a (y_a =
    R_p x_a + t_p, n_k the node's total weight): a block-diagonal part per patch minus
    ``A A^T`` with one column of A per node holding w_a / sqrt(n_k) times each of its
    observations. One sparse product does what expanding every pair of observations of
    each node would (cost and memory growing with the squared track length)."""
    d, m, n = problem.d, problem.num_patches, problem.num_nodes
    mask = problem.shared_mask()  # other observations contribute exactly zero
    p = problem.patch[mask]
    k = problem.node_index[mask]
    w = problem.weight[mask]
    x = (problem.coords[mask] - norm.centroids[p]) / norm.scale
    nk = np.bincount(k, weights=w, minlength=n)
    s = w / np.sqrt(nk[k])
    Q = sp.csr_matrix((s, (p, k)), shape=(m, n))
    rows = (p[:, None] * d + np.arange(d)).ravel()
    A = sp.csr_matrix(((s[:, None] * x).ravel(), (rows, np.repeat(k, d))), shape=(m * d, n))
    at = A.T.tocsr()
    patch_rows = np.arange(m * d)
    S = (sp.diags(np.bincount(p, weights=w, minlength=m)) - Q @ Q.T).tocsr()
    wx = np.stack([np.bincount(p, weights=w * x[:, r], minlength=m) for r in range(d)], 1)
    B_diag = sp.csr_matrix((wx.ravel(), (patch_rows, patch_rows // d)), shape=(m * d, m))
    B = (B_diag - A @ Q.T).tocsr()
    wxx = [
        np.bincount(p, weights=w * x[:, r] * x[:, c], minlength=m)
        for r in range(d)
        for c in range(d)
    ]
    r, c = np.divmod(np.arange(d * d), d)
    C_diag = sp.csr_matrix(
        (
            np.stack(wxx, 1).ravel(),
            ((np.arange(m)[:, None] * d + r).ravel(), (np.arange(m)[:, None] * d + c).ravel()),
        ),
        shape=(m * d, m * d),
    )
    C0 = C_diag - A @ at
    C0 = (0.5 * (C0 + C0.T)).tocsr()
    return C0, B, S
