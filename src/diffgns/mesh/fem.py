"""Taylor-Hood (P2 velocity / P1 pressure) finite-element operators on a :class:`ChannelMesh`.

Everything here is assembled once per mesh with scikit-fem and kept as scipy sparse matrices;
the time stepper (:mod:`diffgns.mesh.cfd`) only does sparse products and factorised solves.
Velocity components share one scalar P2 space, so the velocity is an array ``(n_u, 2)`` and
the component blocks of the mass and stiffness matrices are the same scalar matrix.

Degrees of freedom: P2 dofs ``0..N-1`` are the mesh vertices (in mesh order), the rest are
edge midpoints; P1 dofs are the vertices. Quadrature is exact to degree 5 (7 points per
triangle), enough for the P2 mass matrix (degree 4) and the convection term (degree 5).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from diffgns._extras import require
from diffgns.mesh.geometry import ChannelMesh

_skfem = require("skfem", "cfd")
Basis, BilinearForm, MeshTri, asm = _skfem.Basis, _skfem.BilinearForm, _skfem.MeshTri, _skfem.asm
ElementTriP1, ElementTriP2 = _skfem.ElementTriP1, _skfem.ElementTriP2

_INTORDER = 5


@BilinearForm
def _mass(u, v, w):
    return u * v


@BilinearForm
def _laplace(u, v, w):
    return u.grad[0] * v.grad[0] + u.grad[1] * v.grad[1]


@BilinearForm
def _div_x(u, q, w):
    return u.grad[0] * q


@BilinearForm
def _div_y(u, q, w):
    return u.grad[1] * q


class Convection:
    """Explicit convection vector ``N(u)_k = int (u . grad) u . phi_k dx`` for P2 ``u``.

    The P2 basis values and gradients at all quadrature points are cached as sparse
    interpolation matrices (rows: quadrature points, columns: dofs), so one evaluation is four
    sparse products and no scikit-fem assembly.
    """

    def __init__(self, basis: Basis):
        nb, n_t = basis.element_dofs.shape
        n_q = basis.dx.shape[1]
        rows = np.broadcast_to(np.arange(n_t * n_q).reshape(1, n_t, n_q), (nb, n_t, n_q))
        cols = np.broadcast_to(basis.element_dofs[:, :, None], (nb, n_t, n_q))

        def interp(vals):  # (nb, C, q) -> sparse (C q, n_u), C triangles
            return sp.csr_matrix((vals.ravel(), (rows.ravel(), cols.ravel())),
                                 shape=(n_t * n_q, basis.N))

        self.P = interp(np.stack([basis.basis[i][0].value for i in range(nb)]))
        self.Dx = interp(np.stack([basis.basis[i][0].grad[0] for i in range(nb)]))
        self.Dy = interp(np.stack([basis.basis[i][0].grad[1] for i in range(nb)]))
        self.PwT = (self.P.multiply(basis.dx.reshape(-1, 1))).T.tocsr()  # weights x |J|

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """(n_u, 2) velocity dofs -> (n_u, 2) convection vector (per unit density)."""
        uq = self.P @ u
        conv = uq[:, :1] * (self.Dx @ u) + uq[:, 1:] * (self.Dy @ u)
        return self.PwT @ conv


@dataclass
class Operators:
    """Assembled operators and boundary dof sets of one mesh (per unit density).

    Attributes:
        n_u, n_p: number of P2 (per component) and P1 dofs.
        doflocs: (n_u, 2) P2 dof coordinates, m.
        M, K: (n_u, n_u) P2 mass and stiffness (Laplacian) matrices.
        Bx, By: (n_p, n_u) divergence blocks, ``(B u)_j = int q_j div u``.
        Mp, Kp: (n_p, n_p) P1 mass and stiffness matrices.
        dir_u: P2 dofs with Dirichlet velocity (inflow, walls, cylinder); free_u the rest.
        inflow_u, cyl_u: P2 dofs on the inflow boundary and on the cylinder.
        out_p: P1 dofs on the outflow (p = 0); free_p the rest.
        convection: the :class:`Convection` evaluator.
    """

    n_u: int
    n_p: int
    doflocs: np.ndarray
    M: sp.csr_matrix
    K: sp.csr_matrix
    Bx: sp.csr_matrix
    By: sp.csr_matrix
    Mp: sp.csr_matrix
    Kp: sp.csr_matrix
    dir_u: np.ndarray
    free_u: np.ndarray
    inflow_u: np.ndarray
    cyl_u: np.ndarray
    out_p: np.ndarray
    free_p: np.ndarray
    convection: Convection


def _boundary_facet_sets(mesh: MeshTri, cm: ChannelMesh) -> dict[str, np.ndarray]:
    """Boundary facets split by where their midpoints lie (inflow/outflow/wall/cylinder)."""
    g = cm.geometry
    bf = mesh.boundary_facets()
    mid = mesh.p[:, mesh.facets[:, bf]].mean(axis=1)  # (2, nbf)
    tol = 1e-9 * max(g.length, g.height)
    inflow = mid[0] < tol
    outflow = mid[0] > g.length - tol
    wall = ~inflow & ~outflow & ((mid[1] < tol) | (mid[1] > g.height - tol))
    cyl = ~(inflow | outflow | wall)
    return dict(inflow=bf[inflow], outflow=bf[outflow], wall=bf[wall], cylinder=bf[cyl])


def assemble(cm: ChannelMesh) -> Operators:
    """Assemble the Taylor-Hood operators of ``cm`` (a few tenths of a second for 10k nodes)."""
    mesh = MeshTri(np.ascontiguousarray(cm.nodes.T), np.ascontiguousarray(cm.cells.T))
    bu = Basis(mesh, ElementTriP2(), intorder=_INTORDER)
    bp = Basis(mesh, ElementTriP1(), intorder=_INTORDER)
    facets = _boundary_facet_sets(mesh, cm)

    def dofs(basis, names):
        sets = [basis.get_dofs(facets=facets[n]).all() for n in names if len(facets[n])]
        return np.unique(np.concatenate(sets)) if sets else np.zeros(0, np.int64)

    dir_u = dofs(bu, ["inflow", "wall", "cylinder"])
    out_p = dofs(bp, ["outflow"])
    return Operators(
        n_u=bu.N, n_p=bp.N, doflocs=np.ascontiguousarray(bu.doflocs.T),
        M=asm(_mass, bu).tocsr(), K=asm(_laplace, bu).tocsr(),
        Bx=asm(_div_x, bu, bp).tocsr(), By=asm(_div_y, bu, bp).tocsr(),
        Mp=asm(_mass, bp).tocsr(), Kp=asm(_laplace, bp).tocsr(),
        dir_u=dir_u, free_u=np.setdiff1d(np.arange(bu.N), dir_u),
        inflow_u=dofs(bu, ["inflow"]), cyl_u=dofs(bu, ["cylinder"]),
        out_p=out_p, free_p=np.setdiff1d(np.arange(bp.N), out_p),
        convection=Convection(bu),
    )
