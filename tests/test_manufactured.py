"""Manufactured solutions: the ``mms`` (Wallstedt & Guilkey 2008, axis-aligned) and ``vortex``
(Kamojjala et al. 2013, generalized vortex) scenes.

* their body forces (automatic differentiation of the exact motion) against an independent
  central-difference evaluation of rho0 d2u/dt2 - Div_0 P with the textbook neo-Hookean P, and
  against the closed forms derived by hand (module docstrings);
* the initial state of a phased (deformed-start) MMS against the exact u(X, 0), F(X, 0), v(X, 0);
* 1D MMS convergence under FLIP with quadratic and cubic B-splines: observed order of the
  displacement error >= 1.8 (least-squares slope, computed here);
* the vortex brings its particles back to their start at t = T, more closely on a finer grid.
"""

import math

import jax.numpy as jnp
import numpy as np
import pytest
from cases import central_difference

import jaxmpm as jm
from jaxmpm.scenes.mms import AxisAligned, ManufacturedForce
from jaxmpm.scenes.vortex import Vortex

E, NU, RHO0 = 1.0e4, 0.3, 1.0
LAM = E * NU / ((1 + NU) * (1 - 2 * NU))
MU = E / (2 * (1 + NU))
C = math.sqrt(E / RHO0)
PHASES = (0.0, 2 * math.pi / 3, 4 * math.pi / 3)


# ----------------------------------------------------------------- independent reference (NumPy)
def mms_displacement(X, t, A=0.05):
    """u_i = A sin(pi X_i) sin(c pi t + phi_i) (Wallstedt & Guilkey 2008)."""
    return A * np.sin(np.pi * X) * np.sin(C * np.pi * t + np.array(PHASES[: X.shape[-1]]))


def vortex_displacement(X, t, A=1.0, T=1.0):
    """x = Q(alpha) X, alpha = A g(R) sin^2(pi t / T), g = 1 - 32 (R-1)^2 + 256 (R-1)^4."""
    R = np.linalg.norm(X)
    alpha = A * (1 - 32 * (R - 1) ** 2 + 256 * (R - 1) ** 4) * np.sin(np.pi * t / T) ** 2
    c, s = np.cos(alpha), np.sin(alpha)
    return np.array([c * X[0] - s * X[1], s * X[0] + c * X[1]]) - X


def textbook_piola(F, lam, mu):
    """Compressible neo-Hookean P = mu (F - F^-T) + lambda ln(J) F^-T."""
    Finv_T = np.linalg.inv(F).T
    return mu * (F - Finv_T) + lam * np.log(np.linalg.det(F)) * Finv_T


def fd_body_force(u, X, t, lam, mu, rho0, dx, dt):
    """b = d2u/dt2 - Div_0 P / rho0 by fourth-order central differences of the displacement field
    u(X, t): d2u/dt2 in time, F = I + du/dX, then Div_0 P from differences of P(F(X + s e_J))."""
    d = X.shape[0]
    eye = np.eye(d)
    acc = central_difference(lambda s: u(X, t + s), 0.0, dt, derivative=2, order=4)

    def F_at(Y):
        return eye + np.stack([central_difference(lambda s: u(Y + s * eye[J], t), 0.0, dx, order=4)
                               for J in range(d)], axis=1)

    div = sum(central_difference(lambda s: textbook_piola(F_at(X + s * eye[J]), lam, mu)[:, J], 0.0, dx, order=4)
              for J in range(d))
    return acc - div / rho0


def material():
    return jm.NeoHookean(E=E, nu=NU, density=RHO0)


# ----------------------------------------------------------------- body forces
def test_mms_body_force_matches_finite_differences():
    """3D phased MMS, large amplitude A = 0.05 (axes coupled through ln J): autodiff b vs
    fourth-order central differences (dx = 1e-3, dt = 2e-5 = period/1000: truncation and round-off
    both below 1e-8 of b, whose inertial and stress parts cancel to ~5 %)."""
    rng = np.random.default_rng(0)
    force = ManufacturedForce(AxisAligned(0.05, C, PHASES), material(), np.zeros((1, 3)))
    points, times = rng.uniform(0.02, 0.98, (8, 3)), rng.uniform(0.0, 0.02, 8)
    for X, t in zip(points, times):
        b = np.asarray(force.at(jnp.asarray(X[None]), t))[0]
        ref = fd_body_force(mms_displacement, X, t, LAM, MU, RHO0, dx=1e-3, dt=2e-5)
        np.testing.assert_allclose(b, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_vortex_body_force_matches_finite_differences():
    """Generalized vortex, A = 1 (shear up to 7.1): autodiff b vs fourth-order central differences
    (dx = 1e-3, dt = 1e-3)."""
    rng = np.random.default_rng(1)
    lam, mu = 1000 * 0.3 / (1.3 * 0.4), 1000 / 2.6
    force = ManufacturedForce(Vortex(1.0, 1.0), jm.NeoHookean(E=1000.0, nu=0.3, density=1000.0), np.zeros((1, 2)))
    R, theta, times = rng.uniform(0.76, 1.24, 8), rng.uniform(0, 2 * np.pi, 8), rng.uniform(0, 1, 8)
    for r, th, t in zip(R, theta, times):
        X = np.array([r * np.cos(th), r * np.sin(th)])
        b = np.asarray(force.at(jnp.asarray(X[None]), t))[0]
        ref = fd_body_force(vortex_displacement, X, t, lam, mu, 1000.0, dx=1e-3, dt=1e-3)
        np.testing.assert_allclose(b, ref, rtol=1e-6, atol=1e-6 * np.abs(ref).max())


def test_mms_body_force_matches_closed_form():
    """b_i = pi^2 u_i [mu/rho0 - c^2 - (lambda (ln J - 1) - mu) / (rho0 F_ii^2)] (derived in
    ``jaxmpm.scenes.mms``) in 1D and 3D, amplitude 0.05, on a lattice of points and times."""
    A = 0.05
    for dim in (1, 3):
        X = np.random.default_rng(dim).uniform(0, 1, (64, dim))
        force = ManufacturedForce(AxisAligned(A, C, PHASES[:dim]), material(), X)
        for t in np.linspace(0.0, 0.02, 7):
            u = mms_displacement(X, t, A)
            F = 1 + A * np.pi * np.cos(np.pi * X) * np.sin(C * np.pi * t + np.array(PHASES[:dim]))
            lnJ = np.sum(np.log(F), axis=-1, keepdims=True)
            closed = np.pi**2 * u * (MU / RHO0 - C**2 - (LAM * (lnJ - 1) - MU) / (RHO0 * F**2))
            b = np.asarray(force(jnp.asarray(X), t))
            np.testing.assert_allclose(b, closed, rtol=1e-10, atol=1e-10 * A * C**2)


def test_vortex_body_force_matches_closed_form():
    """b = [R alpha_tt - (mu/rho0)(3 alpha' + R alpha'')] e_theta + [(mu/rho0) R alpha'^2 - R alpha_t^2] e_r
    (derived in ``jaxmpm.scenes.vortex``; Uintah's MMS.cc has the same with h = sin(pi t))."""
    A, T, rho0 = 1.0, 1.0, 1000.0
    mat = jm.NeoHookean(E=1000.0, nu=0.3, density=rho0)
    mu = 1000.0 / 2.6
    rng = np.random.default_rng(2)
    R, theta = rng.uniform(0.75, 1.25, 200), rng.uniform(0, 2 * np.pi, 200)
    X = np.stack([R * np.cos(theta), R * np.sin(theta)], axis=-1)
    force = ManufacturedForce(Vortex(A, T), mat, X)
    s = R - 1
    g, dg, ddg = 1 - 32 * s**2 + 256 * s**4, -64 * s + 1024 * s**3, -64 + 3072 * s**2
    for t in np.linspace(0, T, 9):
        h = np.sin(np.pi * t / T) ** 2
        dh, ddh = np.pi / T * np.sin(2 * np.pi * t / T), 2 * (np.pi / T) ** 2 * np.cos(2 * np.pi * t / T)
        alpha, a_t, a_tt, a_r, a_rr = A * g * h, A * g * dh, A * g * ddh, A * dg * h, A * ddg * h
        b_theta = R * a_tt - mu / rho0 * (3 * a_r + R * a_rr)
        b_r = mu / rho0 * R * a_r**2 - R * a_t**2
        beta = theta + alpha
        closed = np.stack([np.cos(beta) * b_r - np.sin(beta) * b_theta,
                           np.sin(beta) * b_r + np.cos(beta) * b_theta], -1)
        b = np.asarray(force(jnp.asarray(X), t))
        np.testing.assert_allclose(b, closed, rtol=1e-10, atol=1e-10 * np.abs(closed).max() + 1e-12)


def test_phased_mms_starts_on_the_exact_solution():
    """2D MMS with phases (0, 2 pi/3): x = X + u(X, 0), F = I + du/dX(X, 0), V = du/dt(X, 0),
    masses rho0 V0 of the undeformed lattice."""
    A = 0.05
    setup = jm.scene("mms", dim=2, cells=4, amplitude=A)
    X, st = setup.reference.X, setup.state
    phi = np.array(PHASES[:2])
    np.testing.assert_allclose(np.asarray(st.x), X + A * np.sin(np.pi * X) * np.sin(phi), rtol=0, atol=1e-14)
    diag = 1 + A * np.pi * np.cos(np.pi * X) * np.sin(phi)
    np.testing.assert_allclose(np.asarray(st.F), diag[:, :, None] * np.eye(2), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(st.v), A * C * np.pi * np.sin(np.pi * X) * np.cos(phi), rtol=1e-13)
    np.testing.assert_allclose(np.asarray(st.mass), RHO0 * (1 / 4 / 2) ** 2, rtol=1e-13)
    u, v = setup.reference(X, 0.0)  # the Setup's exact solution agrees
    np.testing.assert_allclose(np.asarray(u) + X, np.asarray(st.x), rtol=0, atol=1e-14)
    np.testing.assert_allclose(np.asarray(v), np.asarray(st.v), rtol=1e-13)


# ----------------------------------------------------------------- convergence
CELLS = (8, 16, 32)


def observed_order(h, err):
    """Least-squares slope of log(err) against log(h)."""
    return float(np.polyfit(np.log(h), np.log(err), 1)[0])


@pytest.mark.slow
@pytest.mark.parametrize("shape", [jm.QuadraticBSpline(), jm.CubicBSpline()], ids=["quadratic", "cubic"])
def test_mms_1d_converges_at_second_order(shape):
    """1D MMS, A = 1e-4, FLIP/USL, 2 particles per cell, boundary='extended' (the walls X = 0, 1
    carry the odd continuation of the body, so the B-splines see no wall truncation: with plain
    walls B-splines are first order, see the scene's docstring).  The time step shrinks like h^2
    (cfl = 0.2 * 8/cells) so that USL's O(dt) time error (the half-step lag of the particle
    positions) stays below the spatial error.  Max over the period of the RMS displacement error;
    observed order >= 1.8 (measured: 2.0)."""
    A = 1e-4
    errors = []
    for cells in CELLS:
        setup = jm.scene("mms", dim=1, cells=cells, shape=shape, amplitude=A, boundary="extended",
                         cfl=0.2 * CELLS[0] / cells, frames=20)
        _, history = setup.run()
        ex, _ = setup.reference.errors(history.time, history.x, history.v)
        errors.append(ex.max())
    order = observed_order(1.0 / np.array(CELLS), np.array(errors))
    assert errors[-1] < 0.05 * A, errors
    assert order >= 1.8, (order, errors)


@pytest.mark.slow
def test_vortex_returns_to_start():
    """Generalized vortex (A = 0.1, quadratic B-splines, FLIP): at t = T every particle should be
    back at its reference position.  The tolerance is the discretisation error itself, so the test
    runs two grids and asserts that the RMS return error falls by more than half when h halves
    (measured: 3.0e-2 at h = 1/8, 1.0e-2 at h = 1/16, against a largest exact displacement of 0.1)."""
    errors = []
    for spacing in (0.125, 0.0625):
        setup = jm.scene("vortex", spacing=spacing, amplitude=0.1, frames=10)
        final, _ = setup.run()
        errors.append(float(np.sqrt(np.mean(np.sum((np.asarray(final.x) - setup.reference.X) ** 2, axis=-1)))))
    assert errors[1] < 0.5 * errors[0], errors
