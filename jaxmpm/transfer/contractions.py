"""What P2G scatters: per-particle quantities, each tagged with how it meets the stencil.

A term or scheme does not build per-slot arrays; it hands P2G a per-particle quantity q_p and the
contraction that turns it into a nodal sum over the particles (001 eqs. 16-20, 003 eqs. 2.1, 2.10):

=================  =====================================  ==============  ===========
contraction        nodal sum                              q_p             nodal shape
=================  =====================================  ==============  ===========
:class:`Weighted`    sum_p S_pi q_p                         (N,), (N, C)    (n,), (n, C)
:class:`Gradient`    sum_p q_p G_pi                         (N,)            (n, D)
:class:`Divergence`  sum_p q_p . G_pi  (q_p a C x D matrix)  (N, C, D)       (n, C)
:class:`Affine`      sum_p S_pi q_p (x_i - X_p)              (N, C, D)       (n, C)
:class:`Hoop`        sum_p T_pi q_p  (r-z grids, 001 eq 116) (N,), (N, C)    (n,), (n, C)
:class:`PerSlot`     sum_p c_pi  (per-slot values given)    (K, N), (C,K,N) (n,), (n, C)
=================  =====================================  ==============  ===========

Examples: the lumped mass is ``Weighted(M)``, the momentum ``Weighted(M V)`` (APIC adds
``Affine(M B D^-1)``), the internal force ``Divergence(-V0 tau)``, a body force
``Weighted(M b)``, the material mass gradient of contact ``Gradient(M)``.  A P2G column is one
contraction or a tuple of them (summed); the kernel of the active backend decides how the columns
are scattered (``jaxmpm.transfer.kernels``).  :class:`PerSlot` is the escape hatch for a term that
computes its own per-slot weights (the values of the deprecated ``Term.p2g_columns``).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp


class Contraction(eqx.Module):
    """A per-particle quantity ``value`` and how P2G contracts it with the stencil: the subclass
    names the nodal sum (:class:`Weighted`, :class:`Gradient`, :class:`Divergence`,
    :class:`Affine`, :class:`Hoop`, :class:`PerSlot`).

    Args:
        value: the per-particle quantity q_p, shaped as the subclass asks.
    """

    value: jnp.ndarray

    def width(self, dim: int):
        """The nodal result's trailing shape: () for a scalar per node, (C,) otherwise."""
        raise NotImplementedError(f"{type(self).__name__} must define width")


class Weighted(Contraction):
    """sum_p S_pi q_p: a nodal scalar (n,) or (n, C) (the mass ``Weighted(M)``, the momentum
    ``Weighted(M V)``).

    Args:
        value: q_p, (N,) or (N, C).
    """

    def width(self, dim):
        return self.value.shape[1:]


class Gradient(Contraction):
    """sum_p q_p G_pi of a scalar q (N,): a nodal vector (n, D) (contact's mass gradient
    ``Gradient(M)``).

    Args:
        value: q_p, (N,).
    """

    def width(self, dim):
        return (dim,)


class Divergence(Contraction):
    """sum_p q_p . G_pi, q (N, C, D) contracted on its last axis with G_pi: (n, C) (the internal
    force ``Divergence(-V0 tau)``).

    Args:
        value: q_p, (N, C, D).
    """

    def width(self, dim):
        return self.value.shape[1:2]


class Affine(Contraction):
    """sum_p S_pi q_p (x_i - X_p), q (N, C, D): the affine part of APIC/TPIC/RPIC's momentum, (n, C).

    Args:
        value: q_p, (N, C, D) (APIC: M_p B_p D_p^-1).
    """

    def width(self, dim):
        return self.value.shape[1:2]


class Hoop(Contraction):
    """sum_p T_pi q_p with the hoop shape function T of an axisymmetric stencil (001 eq. 116):
    (n,) or (n, C).

    Args:
        value: q_p, (N,) or (N, C).
    """

    def width(self, dim):
        return self.value.shape[1:]


class PerSlot(Contraction):
    """Per-slot values given: sum_p c_pi, for a term that computes its own per-slot weights.

    Args:
        value: c_pi per stencil slot k (the node ``stencil.index[k, p]``), planar: (K, N) for
            a nodal scalar (n,), (C, K, N) for (n, C).
    """

    def width(self, dim):
        return self.value.shape[:1] if self.value.ndim == 3 else ()


def as_terms(column) -> tuple:
    """A column as a tuple of contractions (one, or several summed)."""
    return tuple(column) if isinstance(column, (tuple, list)) else (column,)
