"""``vortex``: the generalized vortex (Kamojjala, Brannon, Sadeghirad & Guilkey 2013; Uintah
"GeneralizedVortex"), a large-shear manufactured solution on a ring.

Ring R_i = 0.75 <= |X| <= R_o = 1.25 about the origin, compressible neo-Hookean (plane strain).
Each circle R = |X| turns rigidly by the angle

    alpha(R, t) = A g(R) h(t),   g(R) = 1 - 32 (R - 1)^2 + 256 (R - 1)^4 = (4R - 3)^2 (4R - 5)^2,
                                 h(t) = (1 - cos(2 pi t / T)) / 2 = sin^2(pi t / T),

x = Q(alpha) X with Q the rotation.  g and g' vanish at R_i and R_o (so F = I and P = 0 there: the
free surfaces need no traction), and h(0) = h(T) = h'(0) = h'(T) = 0, so the ring starts at rest,
undeformed, and every particle is back at its start, at rest, at t = T.  (Kamojjala et al. use
h = sin(pi t); the sin^2 form makes the initial velocity zero and the return exact at t = T.)

Derivation of the body force (reference polar basis e_R, e_Theta at X; current basis
e_r = Q e_R, e_theta = Q e_Theta; ' = d/dR, dot = d/dt):

* velocity      v = R alpha_dot e_theta
* acceleration  a = R alpha_ddot e_theta - R alpha_dot^2 e_r
* deformation   F = Q (I + gamma e_Theta (x) e_R),  gamma = R alpha'  (a simple shear in the polar
                frame, then the rotation), so J = 1
* stress        J = 1 removes the lambda ln J term: P = mu (F - F^-T); with
                (I + gamma e_Theta (x) e_R)^-T = I - gamma e_R (x) e_Theta,
                P = mu gamma (e_theta (x) e_R + e_r (x) e_Theta)
* divergence    Div_0 (a (x) e_R + b (x) e_Theta) = da/dR + a/R + (1/R) db/dTheta, with
                de_theta/dR = -alpha' e_r and de_r/dTheta = e_theta:
                Div_0 P = mu (gamma' + 2 gamma/R) e_theta - mu gamma alpha' e_r
                        = mu (3 alpha' + R alpha'') e_theta - mu R alpha'^2 e_r
* body force    b = a - Div_0 P / rho0
                  = [R alpha_ddot - (mu/rho0)(3 alpha' + R alpha'')] e_theta
                    + [(mu/rho0) R alpha'^2 - R alpha_dot^2] e_r

(the same expression as Uintah's ``MMS.cc``, whose 3 g' + R g'' = 64 (96R^3 - 240R^2 + 188R - 45)).
The scene evaluates b by automatic differentiation of the exact motion
(:class:`jaxmpm.scenes.mms.ManufacturedForce`, at each particle's reference position); the test
compares it with this closed form.

Material as in Uintah's GeneralizedVortex: E = 1000, nu = 0.3 (mu = 384.6), rho0 = 1000; T = 1;
grid spacing h = 0.05, quadratic B-splines, 2x2 particles per cell,
dt = cfl h / (c_d + max |v|), c_d = sqrt((lambda + 2 mu)/rho0).

Amplitude: default A = 0.1 (peak shear gamma = R alpha' = 0.71), not Uintah's A = 1 (gamma = 7.1).
Measured with A = 1: FLIP, XPIC(5) and APIC, USL or MUSL, cfl 0.1-0.4, lose a particle of the
outer free surface, which runs off the grid by t ~ 0.4-0.7 at h = 1/8, 1/16 and 1/32
(A = 0.5: at h = 1/16 and 1/32) while the kinetic energy grows past its exact value.  A likely
mechanism: once a surface particle separates from the body it feels only its manufactured body
force, which at the free surfaces is large and no longer balanced (b_theta = -(mu/rho0) R alpha'',
g''(R_i) = g''(R_o) = 128).  A = 0.25 runs at h = 0.05 with FLIP, XPIC(5) and APIC but not with
FMPM(4) (nor with FLIP at h = 1/32); A = 0.1 runs with all of them.
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
import numpy as np

from ..core.errors import check
from ..core.grid import Grid
from ..core.particles import Ring, fill
from ..materials import NeoHookean
from ..model.simulation import Simulation
from ..physics.damping import Damping
from ..schemes import FLIP
from ..transfer.shapes import QuadraticBSpline
from ._common import Setup, cast_state, resolve_dtype
from ._options import checked_options
from .manufactured import ManufacturedForce, ManufacturedReference, schedule_exact

INNER, OUTER = 0.75, 1.25


def profile(R):
    """g(R) = 1 - 32 (R - 1)^2 + 256 (R - 1)^4."""
    s = R - 1.0
    return 1.0 - 32.0 * s**2 + 256.0 * s**4


@dataclasses.dataclass(frozen=True)
class Vortex:
    """x = Q(alpha(R, t)) X, alpha = A g(R) sin^2(pi t / T); displacement u = x - X of one point."""

    amplitude: float
    period: float

    def angle(self, R, t):
        return self.amplitude * profile(R) * jnp.sin(jnp.pi * t / self.period) ** 2

    def displacement(self, X, t):
        alpha = self.angle(jnp.sqrt(jnp.sum(X * X)), t)
        c, s = jnp.cos(alpha), jnp.sin(alpha)
        x = jnp.stack([c * X[0] - s * X[1], s * X[0] + c * X[1]])
        return x - X


@checked_options
def vortex(
    scheme=None,
    shape=None,
    spacing: float = 0.05,
    ppc: int = 2,
    amplitude: float = 0.1,
    period: float = 1.0,
    t_end: float | None = None,
    cfl: float = 0.4,
    dt: float | None = None,
    update: str = "USL",
    damping: Damping | None = None,
    dtype=None,
    frames: int = 50,
    E: float = 1000.0,
    nu: float = 0.3,
    density: float = 1000.0,
) -> Setup:
    """The generalized vortex on a grid of spacing ``spacing``; ``t_end`` defaults to the period T,
    when every particle is back at its start.  ``setup.reference(X, t) -> (u, v)`` is the exact
    solution (``setup.reference.X`` the particles' reference positions)."""
    check(spacing > 0 and spacing <= 0.25, f"vortex: spacing = {spacing} must lie in (0, 0.25] (the ring is 0.5 wide)")
    check(period > 0, f"vortex: period = {period} must be positive")
    dtype = resolve_dtype(dtype)
    scheme = FLIP() if scheme is None else scheme
    shape = QuadraticBSpline() if shape is None else shape
    grid = Grid.covering((-OUTER, -OUTER), (OUTER, OUTER), spacing, shape=shape, pad=spacing)
    material = NeoHookean(E=E, nu=nu, density=density)
    motion = Vortex(amplitude=float(amplitude), period=float(period))
    particles = fill(grid, Ring((0.0, 0.0), INNER, OUTER), ppc=ppc)
    X = np.asarray(particles.x, dtype=np.float64)
    sim = Simulation(grid=grid, shape=shape, material=material, scheme=scheme, damping=damping, update=update,
                     body_force=ManufacturedForce(motion, material, X))
    state = cast_state(sim.init(particles), dtype)
    if t_end is None:
        t_end = period
    if dt is None:
        R = np.linspace(INNER, OUTER, 1001)
        top_speed = abs(amplitude) * math.pi / period * float(np.max(R * profile(R)))  # max R |alpha_dot|
        dt = cfl * grid.h / (float(material.wave_speed(2)) + top_speed)
    dt, steps, save_every = schedule_exact(t_end, dt, frames)
    lam, mu = (float(v) for v in material.lame())
    params = dict(spacing=spacing, ppc=ppc, amplitude=amplitude, period=period, inner=INNER, outer=OUTER, E=E, nu=nu,
                  lam=lam, mu=mu, density=density, cfl=cfl, dt=dt, t_end=t_end)
    return Setup("vortex", sim, state, dt, steps, save_every, params, ManufacturedReference(motion, X), particles)
