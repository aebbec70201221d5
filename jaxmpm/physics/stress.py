"""The internal force of the stress, f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20, 003 eq. 2.10)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from ..core.errors import check
from ..core.registry import register_term
from ..transfer.contractions import Divergence, Hoop
from ..transfer.operators import Transfer
from ..transfer.series import series
from .term import Term


class StressDivergence(Term):
    """Internal force f_i = -sum_p V0_p tau_p . G_pi (001 eq. 20, 003 eq. 2.10), tau the
    material's Kirchhoff stress.

    ``xpic=m`` (default 0: off) forms the force from the XPIC(m)-smoothed stress of 000 §3.7,
    tau~ = m S (sigma - sigma*) = S sigma(m), sigma = S+ tau the mass-weighted nodal stress and
    sigma(m) the XPIC series sum_k (-1)^(k+1) C(m,k) (S+S)^(k-1) sigma (000 eqs. 3.67-3.75; the
    seed's three nodal tensors prev/next/tilde are the recursion's term, next term and sum).  It
    removes the stress's null-space part (000 eq. 3.64) before the force extrapolation (the seed's
    eq. 3.76 variant: the particles keep their own stress, which a total-strain law recomputes
    from F every step anyway).  Cost: one more scatter (D^2 columns), m - 1 S+S and one gather.

    On an axisymmetric grid (001 §7) tau is 3x3 in (r, z, theta) and the force is 001 eq. 120,
    f_i = -sum_p V0_p (tau_rz . G_pi + tau_thth T_pi e_r), V0_p per radian: see
    :func:`axisymmetric_stress_divergence`.

    Args:
        xpic: m, the order of the XPIC stress smoothing, an integer >= 0 (default 0: off).
    """

    xpic: int = eqx.field(static=True, default=0)

    def __init__(self, xpic: int = 0):
        check(isinstance(xpic, int) and not isinstance(xpic, bool) and xpic >= 0,
              f"StressDivergence: xpic = {xpic!r}; give the XPIC order m >= 1 of the stress smoothing, or 0 (off)")
        self.xpic = xpic

    @property
    def local(self) -> bool:
        """Without the XPIC smoothing, whose S+ sums run over all particles (jaxmpm.model.chunks)."""
        return self.xpic == 0

    def p2g_quantities(self, sim, state, stencil):
        F = sim.elastic_deformation(state)
        tau = sim.material.stress(F, state.material_state)
        check(jnp.shape(tau) == F.shape,  # shapes are static: checked when the step is traced
              f"{type(sim.material).__name__}.stress (kirchhoff_stress of an elastic law) returned shape "
              f"{jnp.shape(tau)}; the Kirchhoff stress has F's shape {F.shape}, (particles, d, d)")
        if self.xpic:
            check(sim.constraint(tau.dtype).mirror is None,
                  "StressDivergence(xpic=m): the stress smoothing does not fold in a jm.Mirror's images; "
                  "use xpic=0 with mirror planes")
            tau = xpic_stress(stencil, state.mass, tau, self.xpic, sim.field_nodes)
        if sim.grid.axisymmetric:
            return {"force": axisymmetric_stress_divergence(stencil, state.volume0, tau)}
        return {"force": Divergence(-(state.volume0[:, None, None] * tau))}


def axisymmetric_stress_divergence(stencil, volume0, tau):
    """The internal force of 001 eq. 120 (with eq. 118, m_p/rho_0 tau = V0_p tau) as contractions:
    -V0_p [tau_rr tau_rz; tau_rz tau_zz] . G_pi - V0_p (tau_thth, 0) T_pi, G_pi the r-weighted
    gradient (001 eq. 115), T_pi the hoop shape function (001 eq. 116), tau (N, 3, 3) in
    (r, z, theta) order."""
    check(hasattr(stencil, "hoop_view"),
          "StressDivergence: an axisymmetric grid needs the axisymmetric stencil of a jm shape function "
          "(contact's multimaterial stencil has no hoop term: run axisymmetric models without jm.Contact)")
    planar = Divergence(-(volume0[:, None, None] * tau[:, :2, :2]))  # 001 eq. (120)
    hoop = jnp.stack([-volume0 * tau[:, 2, 2], jnp.zeros_like(volume0)], axis=-1)  # (N, 2)
    return (planar, Hoop(hoop))  # - V0 tau_thth T_pi e_r


def xpic_stress(stencil, mass, tau, order: int, num_nodes: int):
    """tau~_p = (S sigma(m))_p, the XPIC(m)-smoothed particle stress (000 eqs. 3.67-3.75)."""
    transfer = Transfer.build(stencil, mass, num_nodes)
    n, d = tau.shape[0], tau.shape[-1]
    sigma = transfer.s_plus(tau.reshape(n, d * d))  # 000 eq. (3.70)/(3.72): sigma_1 = S+ Sigma
    smoothed = series(sigma, order, transfer, None, "binomial")  # 000 eqs. (3.73)-(3.74)
    return transfer.gather(smoothed).reshape(n, d, d)  # 000 eq. (3.75)


register_term("stress", StressDivergence, doc="internal force -sum_p V0_p tau_p . G_pi (001 eq. 20)")
