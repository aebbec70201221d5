"""Taichi's mpm88 substep in any dimension (2D: Taichi's 88-line demo; 3D: the same physics on a cube), the peer
reference of ``benchmarks/gpu.py``.

The scene of jaxmpm's ``mpm88``: APIC transfers with quadratic B-splines, the J-fluid of E = 400, gravity 9.8
along axis 1, one-sided walls 3 cells wide, dt = 2e-4, particle volume (dx/2)^dim and density 1, float32; the same
work per particle-step.  Two terms are written differently (jaxmpm/scenes/mpm88.py): Taichi's MLS force
-V0 tau D^-1 (x_i - X_p) S_pi and J <- J (1 + dt tr C), where jaxmpm has -V0 tau G_pi and J <- det(I + dt L) J.
From the same particles the two agree to round-off while the fluid falls freely (J = 1: the timed windows) and
part after it reaches the floor (experiments/mpm88_vs_taichi.py). Taken from ``../shared/gpu/taichi_mpm.py`` (ours),
which wrote ``python -m taichi example mpm88``'s substep with the dimension as a parameter;
``benchmarks/vs_taichi.py`` keeps its own 2D copy. Taichi is not a dependency of jaxmpm: the callers import it and
skip with a message when it is missing.
"""

from __future__ import annotations

import time

import numpy as np

E, GRAVITY, BOUND, DT = 400.0, 9.8, 3, 2e-4


def substep_kernel(ti, n: int, dim: int, n_grid: int, dt: float = DT, real=None, form: str = "mls"):
    """(substep, (x, v, C, J)): mpm88's substep for ``n`` particles on an ``n_grid``^dim grid of [0, 1]^dim and
    its Taichi fields, in ``real`` (default ``ti.f32``).  ``form="mls"`` is mpm88's own force
    -V0 tau D^-1 (x_i - X_p) S_pi and J <- J (1 + dt tr C); ``form="gradient"`` is jaxmpm's: the force
    -V0 tau G_pi (001 eq. 20) and J <- det(I + dt L) J with L = sum_i v_i (x) G_pi
    (experiments/mpm88_vs_taichi.py).  Everything else is mpm88's."""
    gradient = form == "gradient"
    real = ti.f32 if real is None else real
    dx = 1 / n_grid
    p_vol = (dx * 0.5) ** dim
    p_mass = p_vol
    x = ti.Vector.field(dim, real, n)
    v = ti.Vector.field(dim, real, n)
    C = ti.Matrix.field(dim, dim, real, n)
    J = ti.field(real, n)
    grid_v = ti.Vector.field(dim, real, (n_grid,) * dim)
    grid_m = ti.field(real, (n_grid,) * dim)
    neighbour = (3,) * dim

    @ti.func
    def stencil(p):
        """The particle's first node, its offsets' weights w and their derivatives dw/dX_p, per axis."""
        Xp = x[p] / dx
        base = int(Xp - 0.5)
        fx = Xp - base
        w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1) ** 2, 0.5 * (fx - 0.5) ** 2]
        dw = [(fx - 1.5) / dx, -2 * (fx - 1) / dx, (fx - 0.5) / dx]
        return base, fx, w, dw

    def gradient_of(w, dw, offset):
        """G_pi: one axis's weight derivative times the other axes' weights (``offset`` static)."""
        G = ti.Vector.zero(real, dim)
        for d in ti.static(range(dim)):
            G[d] = 1.0
            for e in ti.static(range(dim)):
                if ti.static(e == d):
                    G[d] *= dw[offset[e]][e]
                else:
                    G[d] *= w[offset[e]][e]
        return G

    # the offset stays a compile-time value (a template), so that it indexes the weight lists; set here, as
    # this module's annotations are strings (from __future__ import annotations), which Taichi does not read
    gradient_of.__annotations__ = {"offset": ti.template()}
    gradient_of = ti.func(gradient_of)

    @ti.kernel
    def substep():
        for node in ti.grouped(grid_m):
            grid_v[node] = ti.zero(grid_v[node])
            grid_m[node] = 0
        ti.loop_config(block_dim=n_grid)
        for p in x:  # P2G
            base, fx, w, dw = stencil(p)
            stress = -dt * 4 * E * p_vol * (J[p] - 1) / dx**2  # mpm88's MLS force, D^-1 = 4 / dx^2
            affine = p_mass * C[p]
            if ti.static(not gradient):
                affine += ti.Matrix.identity(real, dim) * stress
            for offset in ti.static(ti.grouped(ti.ndrange(*neighbour))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                momentum = weight * (p_mass * v[p] + affine @ dpos)
                if ti.static(gradient):  # f dt = -V0 tau G dt, tau = E (J - 1) I
                    momentum += -dt * p_vol * E * (J[p] - 1) * gradient_of(w, dw, offset)
                grid_v[base + offset] += momentum
                grid_m[base + offset] += weight * p_mass
        for node in ti.grouped(grid_m):  # grid update: momentum to velocity, gravity, walls
            if grid_m[node] > 0:
                grid_v[node] /= grid_m[node]
            grid_v[node][1] -= dt * GRAVITY
            cond = (node < BOUND) & (grid_v[node] < 0) | (node > n_grid - BOUND) & (grid_v[node] > 0)
            grid_v[node] = ti.select(cond, 0, grid_v[node])
        ti.loop_config(block_dim=n_grid)
        for p in x:  # G2P
            base, fx, w, dw = stencil(p)
            new_v = ti.zero(v[p])
            new_C = ti.zero(C[p])
            L = ti.zero(C[p])
            for offset in ti.static(ti.grouped(ti.ndrange(*neighbour))):
                dpos = (offset - fx) * dx
                weight = 1.0
                for d in ti.static(range(dim)):
                    weight *= w[offset[d]][d]
                g_v = grid_v[base + offset]
                new_v += weight * g_v
                new_C += 4 * weight * g_v.outer_product(dpos) / dx**2
                if ti.static(gradient):
                    L += g_v.outer_product(gradient_of(w, dw, offset))
            v[p] = new_v
            x[p] += dt * v[p]
            if ti.static(gradient):
                J[p] *= (ti.Matrix.identity(real, dim) + dt * L).determinant()
            else:
                J[p] *= 1 + dt * new_C.trace()
            C[p] = new_C

    return substep, (x, v, C, J)


def run(ti, x0, v0, n_grid: int, steps: int, warmup: int = 20, repeats: int = 3, dt: float = DT):
    """``steps`` substeps from positions ``x0`` and velocities ``v0`` ((N, dim) NumPy arrays) on an ``n_grid``^dim
    grid of [0, 1]^dim, after ``warmup`` substeps that compile the kernel, timed ``repeats`` times from the same
    start.  ``ti`` must be initialised (``ti.init(arch=...)``).  Returns (best wall seconds, final x, final v)."""
    n, dim = x0.shape
    substep, (x, v, C, J) = substep_kernel(ti, n, dim, n_grid, dt)

    def reset():
        x.from_numpy(np.asarray(x0, np.float32))
        v.from_numpy(np.asarray(v0, np.float32))
        J.fill(1)
        C.fill(0)

    return timed(ti, substep, reset, steps, warmup, repeats), x.to_numpy(), v.to_numpy()


def timed(ti, substep, reset, steps: int, warmup: int, repeats: int) -> float:
    """Best wall seconds of ``steps`` calls of the Taichi kernel ``substep`` from the state ``reset()``
    restores, over ``repeats`` timings, after ``warmup`` calls that compile it (``ti.sync()`` around
    each timing: Taichi launches kernels asynchronously)."""
    reset()
    for _ in range(warmup):
        substep()
    ti.sync()
    best = float("inf")
    for _ in range(repeats):
        reset()
        ti.sync()
        start = time.perf_counter()
        for _ in range(steps):
            substep()
        ti.sync()
        best = min(best, time.perf_counter() - start)
    return best
