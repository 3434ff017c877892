"""The two linear-algebra back ends of the Newton core: dense (torch Cholesky) and sparse (SuperLU).

A back end owns the matrix format of every Hessian-like matrix the solver builds (the element
tangent, warped or exact, both with the element-block pattern; diagonal mass and damping terms,
contact blocks): `dense` holds [N d, N d] torch tensors,
`sparse` holds the values [nnz] of one fixed sparsity pattern (element blocks + node blocks,
row-major), so sums and scalings of matrices are plain tensor arithmetic in both. `solve` restricts
a matrix to the free degrees of freedom (the Dirichlet dofs are removed, as in the dense path),
factors it and solves; it returns None when the matrix is not positive definite, and the caller
reports where that happened.

`auto` chooses sparse from `SPARSE_MIN_FREE_DOFS` free unknowns on (docs/simulator.md, "Linear
solver": the 3D crossover measured on one thread with `python -m ggns bench solvers`).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from .fem import ElasticBody

LINEAR_SOLVERS = ("auto", "dense", "sparse")
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


def linear_algebra(choice: str, body: ElasticBody, free: torch.Tensor):
    """The back end named by `choice` (one of LINEAR_SOLVERS); "auto": sparse from
    SPARSE_MIN_FREE_DOFS free unknowns on, dense below."""
    if choice not in LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {LINEAR_SOLVERS}, got {choice!r}")
    if choice == "auto":
        choice = "sparse" if int(free.sum()) >= SPARSE_MIN_FREE_DOFS else "dense"
    return DenseLinearAlgebra(body, free) if choice == "dense" else SparseLinearAlgebra(body, free)
