"""The linear-algebra back ends of the Newton core: dense (torch Cholesky), sparse (SuperLU) and
banded (LAPACK banded Cholesky after a reverse Cuthill-McKee ordering).

A back end owns the matrix format of every Hessian-like matrix the solver builds (the element
tangent, warped or exact, both with the element-block pattern; diagonal mass and damping terms,
contact blocks): `dense` holds [N d, N d] torch tensors,
`sparse` holds the values [nnz] of one fixed sparsity pattern (element blocks + node blocks,
row-major), so sums and scalings of matrices are plain tensor arithmetic in both. `solve` restricts
a matrix to the free degrees of freedom (the Dirichlet dofs are removed, as in the dense path),
factors it and solves; it returns None when the matrix is not positive definite, and the caller
reports where that happened.

`banded` keeps the sparse back end's matrix format and replaces only the factorization: the free
block's pattern is ordered once per `Simulator` by reverse Cuthill-McKee, and every Newton matrix is
factored by `scipy.linalg.cholesky_banded` over that bandwidth (cost ~ n b^2, no fill analysis, no
ordering per solve). It pays off where the ordered bandwidth b is small next to the unknowns n:
the cavity's tube (one element thick, 25 nodes per ring: b = 224 of 2,100), and also the 10 x 6 x 6
tet block of `bench solvers` (717 unknowns: 0.96 ms per factor + solve against SuperLU's 2.80,
docs/simulator.md); a compact mesh's bandwidth grows as n^(2/3), so on large compact meshes sparse
should win again (not measured). Its results equal the sparse back end's to round-off (not bit for
bit), which is why `auto` does not pick it: the plate's and the tissue's data stay bit for bit. LAPACK runs on one BLAS thread (threadpoolctl): the simulator is
single-threaded by design (generation runs one trajectory per worker process), and OpenBLAS's own
threads beside busy cores made a cavity trajectory 2-3x slower than one thread (a throwaway
script, docs/simulator.md).

`auto` chooses sparse from `SPARSE_MIN_FREE_DOFS` free unknowns on (docs/simulator.md, "Linear
solver": the 3D crossover measured on one thread with `python -m ggns bench solvers`); it never
chooses banded (the cavity presets name it).
"""
from __future__ import annotations

import numpy as np
import scipy.linalg
import scipy.sparse
import scipy.sparse.csgraph
import scipy.sparse.linalg
import threadpoolctl
import torch

from .fem import ElasticBody

LINEAR_SOLVERS = ("auto", "dense", "sparse", "banded")
SPARSE_MIN_FREE_DOFS = 200  # "auto" picks sparse from this many free unknowns on


class DenseLinearAlgebra:
    """Dense [N d, N d] matrices, Cholesky of the free block (torch.linalg.cholesky_ex)."""

    name = "dense"

    def __init__(self, body: ElasticBody, free: torch.Tensor):
        self.body, self.free = body, free
        self.size = body.num_nodes * body.dim
        self.node_dofs = torch.arange(self.size).view(-1, body.dim)

    def stiffness(self, R: torch.Tensor) -> torch.Tensor:
        """Assembled warped stiffness R K0 R^T for element rotations R [C, d, d]."""
        return self.assemble(self.body.warped_stiffness(R))

    def assemble(self, blocks: torch.Tensor) -> torch.Tensor:
        """The matrix of element blocks flattened to match the body's (hess_rows, hess_cols)."""
        nd = self.size
        K = torch.zeros(nd * nd, dtype=torch.float64)
        K.index_add_(0, self.body.hess_rows * nd + self.body.hess_cols, blocks)
        return K.view(nd, nd)

    def diag(self, values: torch.Tensor) -> torch.Tensor:
        return torch.diag(values)

    def add_node_blocks(self, H: torch.Tensor, blocks: torch.Tensor) -> torch.Tensor:
        """H plus one d x d block per node (blocks [N, d, d]) on the diagonal; in place."""
        H[self.node_dofs[:, :, None], self.node_dofs[:, None, :]] += blocks
        return H

    def matvec(self, A: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        return A @ v

    def solve(self, H: torch.Tensor, g: torch.Tensor) -> torch.Tensor | None:
        """H[free, free]^-1 g for g over the free dofs; None if that block is not positive definite."""
        L, info = torch.linalg.cholesky_ex(H[self.free][:, self.free])
        if info.item() != 0:
            return None
        return torch.cholesky_solve(g[:, None], L)[:, 0]


class SparseLinearAlgebra:
    """Matrices as values over one fixed pattern; SuperLU (scipy.sparse.linalg.splu) of the free
    block with a symmetric fill-reducing ordering and diagonal pivots, i.e. an LDL^T factorization."""

    name = "sparse"

    def __init__(self, body: ElasticBody, free: torch.Tensor):
        self.body, self.free = body, free
        n, d = body.num_nodes, body.dim
        nd = self.size = n * d
        node_dofs = torch.arange(nd).view(n, d)
        block_rows = node_dofs[:, :, None].expand(n, d, d).reshape(-1)
        block_cols = node_dofs[:, None, :].expand(n, d, d).reshape(-1)
        keys = torch.cat([body.hess_rows * nd + body.hess_cols, block_rows * nd + block_cols])
        unique, inverse = torch.unique(keys, sorted=True, return_inverse=True)  # row-major order
        self.nnz = len(unique)
        self.element_positions = inverse[: len(body.hess_rows)]
        self.block_positions = inverse[len(body.hess_rows):]
        self.diag_positions = self.block_positions.view(n, d, d).diagonal(dim1=1, dim2=2).reshape(-1)
        self.rows, self.cols = unique // nd, unique % nd
        # the free block in CSR form (its own transpose, so also CSC), numbered over the free dofs
        self.keep = free[self.rows] & free[self.cols]
        renumber = torch.cumsum(free.long(), 0) - 1
        rows, cols = renumber[self.rows[self.keep]], renumber[self.cols[self.keep]]
        self.num_free = int(free.sum())
        self.indices = cols.numpy().astype(np.int32)
        self.indptr = np.concatenate([[0], np.cumsum(np.bincount(rows.numpy(), minlength=self.num_free))]).astype(np.int32)

    def stiffness(self, R: torch.Tensor) -> torch.Tensor:
        return self.assemble(self.body.warped_stiffness(R))

    def assemble(self, blocks: torch.Tensor) -> torch.Tensor:
        """Element blocks (flattened as the body's hess_rows, hess_cols) as pattern values."""
        K = torch.zeros(self.nnz, dtype=torch.float64)
        K.index_add_(0, self.element_positions, blocks)
        return K

    def diag(self, values: torch.Tensor) -> torch.Tensor:
        D = torch.zeros(self.nnz, dtype=torch.float64)
        D[self.diag_positions] = values
        return D

    def add_node_blocks(self, H: torch.Tensor, blocks: torch.Tensor) -> torch.Tensor:
        H.index_add_(0, self.block_positions, blocks.reshape(-1))
        return H

    def matvec(self, A: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(self.size, dtype=torch.float64)
        out.index_add_(0, self.rows, A * v[self.cols])
        return out

    def to_dense(self, A: torch.Tensor) -> torch.Tensor:
        """The [N d, N d] matrix whose pattern values are A (for tests and checks)."""
        out = torch.zeros(self.size, self.size, dtype=torch.float64)
        out[self.rows, self.cols] = A
        return out

    def solve(self, H: torch.Tensor, g: torch.Tensor) -> torch.Tensor | None:
        A = scipy.sparse.csc_matrix((H[self.keep].numpy(), self.indices, self.indptr), shape=(self.num_free,) * 2)
        try:
            lu = scipy.sparse.linalg.splu(A, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                          options={"SymmetricMode": True})
        except RuntimeError:  # an exactly zero pivot: singular
            return None
        # symmetric permutation and positive pivots: A = P L D L^T P^T with D > 0, i.e. positive definite
        if not (np.array_equal(lu.perm_r, lu.perm_c) and (lu.U.diagonal() > 0).all()):
            return None
        return torch.from_numpy(lu.solve(g.numpy()))


_blas = None  # the loaded BLAS libraries (threadpoolctl), found on the first banded solve


def one_blas_thread():
    """A context in which BLAS/LAPACK calls run on one thread."""
    global _blas
    if _blas is None:
        _blas = threadpoolctl.ThreadpoolController().select(user_api="blas")
    return _blas.limit(limits=1)


class BandedLinearAlgebra(SparseLinearAlgebra):
    """The sparse back end's matrices; the free block ordered once by reverse Cuthill-McKee and
    factored by LAPACK's banded Cholesky (module docstring)."""

    name = "banded"

    def __init__(self, body: ElasticBody, free: torch.Tensor):
        super().__init__(body, free)
        n = self.num_free
        pattern = scipy.sparse.csr_matrix((np.ones(len(self.indices)), self.indices, self.indptr), shape=(n, n))
        order = scipy.sparse.csgraph.reverse_cuthill_mckee(pattern, symmetric_mode=True)
        position = np.empty(n, dtype=np.int64)
        position[order] = np.arange(n)
        self.order = torch.from_numpy(order.astype(np.int64))
        rows = position[np.repeat(np.arange(n), np.diff(self.indptr))]  # ordered row, column of each kept entry
        cols = position[self.indices]
        self.bandwidth = int(np.abs(rows - cols).max()) if len(rows) else 0
        upper = rows <= cols  # LAPACK's upper band storage: ab[b + i - j, j] = A[i, j] for i <= j
        # the pattern values (over all of H) that fill the band, and where
        self.band_values = torch.nonzero(self.keep).flatten()[torch.from_numpy(upper)]
        self.band_index = torch.from_numpy((self.bandwidth + rows[upper] - cols[upper]) * n + cols[upper])

    def solve(self, H: torch.Tensor, g: torch.Tensor) -> torch.Tensor | None:
        n = self.num_free
        band = torch.zeros((self.bandwidth + 1) * n, dtype=torch.float64)
        band[self.band_index] = H[self.band_values]
        with one_blas_thread():
            try:
                factor = scipy.linalg.cholesky_banded(band.view(self.bandwidth + 1, n).numpy(), lower=False,
                                                      check_finite=False)
            except np.linalg.LinAlgError:  # a non-positive pivot: not positive definite
                return None
            y = scipy.linalg.cho_solve_banded((factor, False), g[self.order].numpy(), check_finite=False)
        x = torch.empty_like(g)
        x[self.order] = torch.from_numpy(y)
        return x


BACK_ENDS = {"dense": DenseLinearAlgebra, "sparse": SparseLinearAlgebra, "banded": BandedLinearAlgebra}


def linear_algebra(choice: str, body: ElasticBody, free: torch.Tensor):
    """The back end named by `choice` (one of LINEAR_SOLVERS); "auto": sparse from
    SPARSE_MIN_FREE_DOFS free unknowns on, dense below."""
    if choice not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {choice!r}")
    if choice == "auto":
        choice = "sparse" if int(free.sum()) >= SPARSE_MIN_FREE_DOFS else "dense"
    return BACK_ENDS[choice](body, free)
