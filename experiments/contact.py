"""Multimaterial contact (issue 12; 000 ch. 4, 003 ch. 3): disks, bars_impact, slide, and stick vs one field.

Four measurements, all float64 with the USL update:

1. **disks** (Sulsky, Chen & Schreyer 1994; the scene's defaults: h = 0.05, 2x2 ppc, dt = 1e-3,
   uGIMP, grid padded by two cells, t_end = 4), every particle update (FLIP, PIC, the 0.99 blend,
   XPIC(2), XPIC(5), FMPM(4), APIC) x contact law (``none`` = one velocity field, ``stick``,
   ``frictionless``, ``coulomb`` with mu = 0.3; the scene's contact options otherwise: normal
   "average" and its separation criterion, printed under the table).  Per run:

   * *min E/E0* (total energy, kinetic + strain) over two windows: *shared nodes*, the frames where
     the two disks share a grid node (some node receives mass from both; the window of
     experiments/disks_schemes.py, the same for every law, ``none`` included), and the *force
     window*, where the contact force on disk 0 (``history.by_material["contact_force"]``) exceeds
     1e-3 of its peak: the frames where the law actually exchanges momentum (on the nodes the
     separation criterion accepts; ``frictionless``/``coulomb`` only while the disks approach there);
   * *max E/E0* over the run and when (a contact law can add energy), and E(t = 4)/E0 after
     separation (``—`` if the run did not reach t = 4);
   * *separate*: the distance d between the disks' centres of mass has its minimum inside the run
     and has grown by more than one cell h by the end; the *rebound ratio* is d'(end) / |d'(0)|
     (d' over the last 0.25 time units; 1 for a perfectly elastic rebound of rigid disks);
   * *max |p - p0|*: the drift of the total linear momentum, relative to sum_p M_p |V_p| at t = 0
     (the total momentum is zero: the disks move at +-(0.1, 0.1));
   * run time (s; the second call of the compiled run) and jit time (first call minus second).

   An unstable run (``jm.InstabilityError``: NaN, J <= 0 or particles leaving the grid) is reported
   with its step, time and cause, and its histories are kept up to the last frame before it.  The
   rebounding disks reach the grid edge near t = 4 (a disk started touching the unit square), so
   "particles left the grid" there is the scene's geometry, not the scheme.

2. **stick vs one field** (003 §3.3: the XPIC/FMPM contact update "does not revert exactly to
   single material mode when the interface is perfect"): max_p |x_stick - x_none| / max_p |x_none|
   at t = 2 (and the same for velocities, and the maximum over all frames up to t = 2), every scheme
   of 1 and FMPM(2), run to t = 2 with ``contact="stick"`` and no separation criterion (the law on every node
   both disks reach: without the criterion, a perfect interface is what one shared field does) and
   with ``contact="none"``.  PIC and FLIP revert to round-off (000 §4.6); XPIC(m) and FMPM(k) do
   not, because S+^a averages over one material's particles.

3. **bars_impact** (the scene's defaults: L = 1, E = 100, rho = 1, v0 = 0.1, c = 10, linear shape
   functions, 2 ppc, dt = 0.1 h/c, t_end = 4L/c), FLIP, XPIC(2), FMPM(2) with ``frictionless`` and
   ``none`` contact, at 32 (default), 64 and 128 cells a bar, with the scene's linear shape functions
   and with uGIMP (linear ones invert particles in several of these runs); one frame per step.  Exit velocities
   are the bars' mean velocities at t_end (after separation only contact acts on a bar, so they are
   constant), as the error max(|v_left + v0|, |v_right - v0|) / v0 against the exchange.  Contact
   duration (as tests/test_contact_scenes.py): the last time the left bar's momentum changes in a
   step by more than 1e-3 rho c v0 dt, against 2L/c.  With one field (``none``) the bars cannot
   part; the "duration" there is when the interface force last exceeded the threshold.

4. **slide** (the scene's defaults: theta = 30°, uGIMP, normal "first", h = 0.025, t_end = 0.315),
   FLIP, PIC, XPIC(2) with Coulomb friction mu = 0, 0.2, 0.7: the block's centre-of-mass
   displacement along x at t_end against ``setup.reference`` (g (sin theta - mu cos theta) t^2 / 2;
   0 for mu = 0.7 > tan 30°, where the displacement is given as a fraction of the frictionless one).

Writes ``experiments/results/contact[_quick].md`` (the tables), ``contact[_quick]_disks.csv``
(energy histories: total, per-material kinetic, centre distance, contact force on disk 0; every
other frame), ``contact[_quick]_bars.csv`` (the bars' mean velocities, 200 times a run),
``contact[_quick]_slide.csv`` (block displacement and exact) and ``contact[_quick]_disks.png``
(total energy per law for each scheme), and prints the tables.

    python experiments/contact.py            # everything above (about 4 min on 2 CPU cores)
    python experiments/contact.py --quick    # disks to t = 3 with FLIP, PIC, XPIC(2); bars at 32
                                             # cells; slide FLIP; smoke test (about a minute)
"""

from __future__ import annotations

import argparse
import csv
import math
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxmpm as jm  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
LAWS = {"none": {}, "stick": {}, "frictionless": {}, "coulomb": {"friction": 0.3}}
LAW_LABEL = {"none": "none (one field)", "stick": "stick", "frictionless": "frictionless", "coulomb": "coulomb μ=0.3"}
T_COMPARE = 2.0  # stick vs one field
FORCE_THRESHOLD = 1e-3  # force window: |F contact| > this x its peak
REBOUND_SPAN = 0.25
# the separation criterion "off": (x^1 - x^0) . n <= 1e6 h holds on every node both disks reach (the
# disks scene's option check refuses separation=None, although jm.Contact(separation=None) is "off")
NO_SEPARATION = 1e6  # d' at the end: over the last REBOUND_SPAN time units


def disks_schemes(quick: bool):
    """Label -> scheme, in table order."""
    if quick:
        return {"FLIP": jm.FLIP(), "PIC": jm.PIC(), "XPIC(2)": jm.XPIC(order=2)}
    return {
        "FLIP": jm.FLIP(),
        "PIC": jm.PIC(),
        "blend 0.99": jm.FLIP(beta=0.99),
        "XPIC(2)": jm.XPIC(order=2),
        "XPIC(5)": jm.XPIC(order=5),
        "FMPM(4)": jm.FMPM(order=4),
        "APIC": jm.APIC(),
    }


def short_cause(err) -> str:
    return err.cause.split(" (")[0]


def timed_run(setup, save_every=None):
    """(history, InstabilityError or None, run s, jit s): the compiled run is called twice, the
    first call compiles; a failed run is repeated with check_stability=False for its frames."""
    save_every = setup.save_every if save_every is None else save_every

    def once():
        try:
            _, history = setup.sim.run(setup.state, setup.dt, setup.steps, save_every)
            return history, None
        except jm.InstabilityError as err:
            _, history = setup.sim.run(setup.state, setup.dt, setup.steps, save_every, check_stability=False)
            return history, err

    start = time.perf_counter()
    history, failure = once()
    jax.block_until_ready(history)
    first = time.perf_counter() - start
    start = time.perf_counter()
    history, failure = once()
    jax.block_until_ready(history)
    run_s = time.perf_counter() - start
    return history, failure, run_s, max(0.0, first - run_s)


def status(failure) -> str:
    if failure is None:
        return "ok"
    return f"unstable at step {failure.step} (t = {failure.time:.3f}): {short_cause(failure)}"


# ------------------------------------------------------------------------------------------ 1. disks
def shared_node_frames(setup, x_frames) -> np.ndarray:
    """True at frames where the two disks share a grid node (both put mass on it): the stencils of
    all frames at once (one vmapped call), then a per-frame node count per disk."""
    n_first = setup.params["n_first"]
    shape, grid = setup.sim.shape, setup.sim.grid

    @jax.jit
    def stencils(x):
        def one(xf):
            st = shape.stencil(grid, xf)
            return st.index, st.weight

        return jax.vmap(one)(x)

    index, weight = (np.asarray(a) for a in stencils(jax.numpy.asarray(x_frames)))  # (T, K, N)
    num = grid.num_nodes
    frames = np.arange(index.shape[0])[:, None, None]
    out = []
    for body in (slice(None, n_first), slice(n_first, None)):
        hit = np.zeros((index.shape[0], num), bool)
        idx, w = index[..., body], weight[..., body]
        hit[np.broadcast_to(frames, idx.shape)[w > 0], idx[w > 0]] = True
        out.append(hit)
    return np.any(out[0] & out[1], axis=1)


def window(mask, times):
    if not mask.any():
        return None
    first, last = np.flatnonzero(mask)[[0, -1]]
    return float(times[first]), float(times[last])


def run_disks(label, scheme, law, t_end, frames, **options) -> dict:
    """One disks run; ``options`` go to the scene (e.g. ``separation=None``)."""
    setup = jm.scene("disks", scheme=scheme, dtype="f64", update="USL", contact=law, t_end=t_end, frames=frames,
                     **LAWS[law], **options)
    history, failure, run_s, jit_s = timed_run(setup)
    t = np.asarray(history.time)
    keep = np.ones_like(t, bool) if failure is None else t < failure.time
    n = setup.params["n_first"]
    m = np.asarray(setup.state.mass)
    x = np.asarray(history.x)[keep]
    v = np.asarray(history.v)[keep]
    com0 = np.einsum("tpd,p->td", x[:, :n], m[:n]) / m[:n].sum()
    com1 = np.einsum("tpd,p->td", x[:, n:], m[n:]) / m[n:].sum()
    kin = 0.5 * m * np.sum(v**2, axis=-1)
    h = dict(time=t[keep], kinetic=np.asarray(history.kinetic)[keep], strain=np.asarray(history.strain)[keep],
             kinetic_0=kin[:, :n].sum(1), kinetic_1=kin[:, n:].sum(1),
             distance=np.linalg.norm(com1 - com0, axis=-1), momentum=np.asarray(history.momentum)[keep],
             x=x, v=v)
    h["total"] = h["kinetic"] + h["strain"]
    force = history.by_material.get("contact_force")
    h["force_0"] = (np.zeros((keep.sum(), 2)) if force is None else np.asarray(force)[keep, 0])
    if history.by_material:  # the per-material kinetic energy of the library equals ours
        np.testing.assert_allclose(np.asarray(history.by_material["kinetic"])[keep],
                                   np.stack([h["kinetic_0"], h["kinetic_1"]], 1), rtol=1e-10, atol=0)
    return dict(label=label, law=law, setup=setup, h=h, failure=failure, run_s=run_s, jit_s=jit_s)


def at_time(h, key, t):
    times = h["time"]
    if times.size == 0 or times[-1] < t - 1e-9:
        return None
    return h[key][np.argmin(np.abs(times - t))]


def summarise_disks(res, t_end) -> dict:
    h, setup = res["h"], res["setup"]
    e0 = float(h["total"][0])
    t = h["time"]
    row = dict(scheme=res["label"], law=res["law"], e0=e0, run_s=res["run_s"], jit_s=res["jit_s"],
               status=status(res["failure"]), separation=setup.params.get("separation"),
               frames=setup.steps // setup.save_every)
    shared = shared_node_frames(setup, h["x"])
    row["shared"] = window(shared, t)
    row["min_contact"] = float(h["total"][shared].min() / e0) if shared.any() else None
    f = np.linalg.norm(h["force_0"], axis=-1)
    row["force_window"] = window(f > FORCE_THRESHOLD * f.max(), t) if f.max() > 0 else None
    if row["force_window"] is None:
        row["min_force"] = None
    else:
        inside = (t >= row["force_window"][0] - 1e-9) & (t <= row["force_window"][1] + 1e-9)
        row["min_force"] = float(h["total"][inside].min() / e0)
    k_max = int(np.argmax(h["total"]))
    row["max_e"], row["t_max_e"] = float(h["total"][k_max] / e0), float(t[k_max])
    end = at_time(h, "total", t_end)
    row["after"] = None if end is None else float(end / e0)
    d = h["distance"]
    k = int(np.argmin(d))
    span = t >= t[-1] - REBOUND_SPAN
    approach = abs((d[1] - d[0]) / (t[1] - t[0]))
    rate = np.polyfit(t[span], d[span], 1)[0] if span.sum() >= 2 else float("nan")
    row["d_min"], row["t_d_min"], row["d_end"] = float(d[k]), float(t[k]), float(d[-1])
    row["separate"] = bool(0 < k < d.size - 1 and d[-1] - d[k] > setup.params["spacing"] and rate > 0)
    row["rebound"] = float(rate / approach)
    scale = float(np.sum(np.asarray(setup.state.mass) * np.linalg.norm(np.asarray(setup.state.v), axis=-1)))
    row["dp"] = float(np.max(np.abs(h["momentum"] - h["momentum"][0])) / scale)
    row["t_last"] = float(t[-1])
    return row


def fmt(value, spec="{:.4f}"):
    return "—" if value is None else spec.format(value)


def fmt_window(w):
    return "—" if w is None else f"{w[0]:.2f}–{w[1]:.2f}"


def disks_table(rows, t_end) -> str:
    lines = [
        f"| scheme | contact | min E/E0, shared nodes | min E/E0, force window | max E/E0 (at t) | E(t={t_end:g})/E0 "
        "| shared nodes (t) "
        "| force window (t) "
        "| separate (d_min at t → d_end; rebound) | max abs(p − p0) rel. | run (s) | jit (s) | status |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sep = (f"{'yes' if r['separate'] else 'no'} ({r['d_min']:.3f} at {r['t_d_min']:.2f} → {r['d_end']:.3f}; "
               f"{r['rebound']:.2f})")
        lines.append(
            f"| {r['scheme']} | {LAW_LABEL[r['law']]} | {fmt(r['min_contact'])} | {fmt(r['min_force'])} "
            f"| {r['max_e']:.4f} ({r['t_max_e']:.2f}) | {fmt(r['after'])} "
            f"| {fmt_window(r['shared'])} | {fmt_window(r['force_window'])} | {sep} | {r['dp']:.1e} "
            f"| {r['run_s']:.2f} | {r['jit_s']:.2f} | {r['status']} |")
    lines.append(
        f"\nE0 = {rows[0]['e0']:.6g} (initial kinetic energy); t_end = {t_end:g}; float64, USL, uGIMP (grid padded by "
        f"two cells), h = 0.05, 2x2 ppc, dt = 1e-3, {rows[0]['frames']} frames; the scene's contact options: normal "
        f"'average', separation criterion {rows[-1]['separation']} cell(s).  *Shared nodes*: frames "
        "where both disks put mass on a node (experiments/disks_schemes.py's contact window, the same for every law); "
        f"*force window*: the contact force on disk 0 above {FORCE_THRESHOLD:g} of its peak (where the law "
        "exchanges momentum; none with one field).  *Separate*: the centres' distance d passes a minimum and grows by "
        f"more than h by the end; rebound = d'(end) / abs(d'(0)) (d' fitted over the last {REBOUND_SPAN:g}).  "
        "max abs(p − p0): total momentum drift over the run / sum M abs(V) at t = 0.  The blend reuses FLIP's "
        "compiled step (beta is an array leaf), so its jit column is timing noise.")
    return "\n".join(lines)


# ------------------------------------------------------------------------- 2. stick vs one field
def relative_difference(a, b):
    return float(np.max(np.abs(a - b)) / np.max(np.abs(a)))


def stick_vs_single(runs, t_compare) -> list[dict]:
    """runs: {(label, law): run_disks result} with laws "none" and "stick"."""
    rows = []
    for label in dict.fromkeys(lbl for lbl, _ in runs):
        single, stick = runs[(label, "none")]["h"], runs[(label, "stick")]["h"]
        frames = min(single["time"].size, stick["time"].size)
        upto = single["time"][:frames] <= t_compare + 1e-9
        k = int(np.argmin(np.abs(single["time"] - t_compare)))
        reached = single["time"][-1] >= t_compare - 1e-9 and stick["time"][-1] >= t_compare - 1e-9
        rows.append(dict(
            scheme=label,
            x_at=relative_difference(single["x"][k], stick["x"][k]) if reached else None,
            v_at=relative_difference(single["v"][k], stick["v"][k]) if reached else None,
            x_max=relative_difference(single["x"][:frames][upto], stick["x"][:frames][upto]),
            v_max=relative_difference(single["v"][:frames][upto], stick["v"][:frames][upto]),
        ))
    return rows


def stick_table(rows, t_compare) -> str:
    lines = [
        f"| scheme | positions at t={t_compare:g} | velocities at t={t_compare:g} "
        f"| positions, max over t ≤ {t_compare:g} "
        f"| velocities, max over t ≤ {t_compare:g} |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(f"| {r['scheme']} | {fmt(r['x_at'], '{:.1e}')} | {fmt(r['v_at'], '{:.1e}')} "
                     f"| {r['x_max']:.1e} | {r['v_max']:.1e} |")
    lines.append(
        "\nmax_p abs(a_stick − a_none) / max_p abs(a_none) (positions x, velocities v), disks as in the table above "
        "(contact='stick' with the separation criterion off (separation=1e6 cells) -- the law on every node both "
        "disks reach, as one field couples "
        "them -- vs contact='none', same scheme).  The disks share nodes from t ≈ 1.04.")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- 3. bars
def run_bars(label, scheme, contact, cells, shape="linear") -> dict:
    setup = jm.scene("bars_impact", scheme=scheme, dtype="f64", contact=contact, cells=cells, shape=shape)
    history, failure, run_s, jit_s = timed_run(setup, save_every=1)
    p = setup.params
    n = p["n_first"]
    m = np.asarray(setup.state.mass)
    t = np.asarray(history.time)
    keep = np.ones_like(t, bool) if failure is None else t < failure.time  # frames before a failure
    t = t[keep]
    v = np.asarray(history.v)[keep, :, 0]
    left, right = v[:, :n] @ m[:n] / m[:n].sum(), v[:, n:] @ m[n:] / m[n:].sum()
    force = -np.diff(left * m[:n].sum()) / np.diff(t) / p["contact_stress"]
    active = np.flatnonzero(np.abs(force) > 1e-3)
    end = float(t[active[-1] + 1]) if active.size else None
    v0 = p["v0"]
    exit_left, exit_right = p["exit_velocities"]
    done = failure is None
    return dict(scheme=label, contact=contact, cells=cells, shape=shape, steps=setup.steps,
                left=float(left[-1]) if done else None, right=float(right[-1]) if done else None,
                exit_error=max(abs(left[-1] - exit_left), abs(right[-1] - exit_right)) / v0 if done else None,
                duration=end, duration_ratio=None if end is None else end / p["contact_duration"],
                momentum=float(np.max(np.abs(left + right))) / v0, run_s=run_s, jit_s=jit_s,
                status=status(failure), time=t, v_left=left, v_right=right)


def exit_velocities(r) -> str:
    return "—" if r["left"] is None else f"{r['left']:+.5f}, {r['right']:+.5f}"


def bars_table(rows) -> str:
    lines = [
        "| shape | scheme | contact | cells/bar | exit v (left, right) | exit error / v0 | contact ends at t "
        "| duration / (2L/c) | run (s) | jit (s) | status |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['shape']} | {r['scheme']} | {r['contact']} | {r['cells']} | {exit_velocities(r)} "
            f"| {fmt(None if r['exit_error'] is None else 100 * r['exit_error'], '{:.2f} %')} | {fmt(r['duration'])} "
            f"| {fmt(r['duration_ratio'], '{:.4f}')} | {r['run_s']:.2f} | {r['jit_s']:.2f} | {r['status']} |")
    lines.append(
        "\nbars_impact: L = 1, E = 100, rho = 1, v0 = 0.1, c = 10, 2L/c = 0.2, t_end = 4L/c = 0.4, 2 ppc, "
        "dt = 0.1 h/c; linear shape functions (the scene's default), and uGIMP because linear ones invert "
        "particles (J <= 0) in several runs; exact exit velocities (−0.1, +0.1).  Exit error: max over the bars of "
        "abs(v_exit − exchanged) / v0.  Contact end: the last step where the left bar's momentum changes by more "
        "than 1e-3 rho c v0 dt.  With one field ('none') the bars cannot part: they vibrate as one bar of length "
        "2L, and the 'contact end' is the last time the interface force exceeded that threshold.")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------- 4. slide
def run_slide(label, scheme, mu, damping=None, ramp=0.0) -> dict:
    setup = jm.scene("slide", scheme=scheme, dtype="f64", contact="coulomb", friction=mu, damping=damping, ramp=ramp)
    history, failure, run_s, jit_s = timed_run(setup)
    n = setup.params["n_first"]
    m = np.asarray(setup.state.mass)[n:]
    t = np.asarray(history.time)
    com = np.asarray(history.x)[:, n:, 0] @ m / m.sum()
    d = com - com[0]
    theta = math.radians(setup.params["theta"])
    r = setup.params["ramp"]  # the frictionless exact displacement, under the ramped load if any
    frictionless = setup.params["gravity"] * math.sin(theta) * (0.5 * t[-1] ** 2 if r == 0 else
                                                                0.5 * t[-1] ** 2 - 0.5 * r * t[-1] + r * r / 6)
    exact = float(setup.reference(t[-1]))
    return dict(scheme=label, mu=mu, t_end=float(t[-1]), d=float(d[-1]), exact=exact,
                error=None if exact == 0 else d[-1] / exact - 1, of_frictionless=d[-1] / frictionless,
                cells=d[-1] / setup.params["spacing"], run_s=run_s, jit_s=jit_s, status=status(failure),
                time=t, displacement=d, reference=setup.reference(t))


def slide_table(rows) -> str:
    lines = [
        "| scheme | μ | displacement at t_end | exact | error | / frictionless exact | run (s) | jit (s) | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        err = "— (stuck)" if r["error"] is None else f"{100 * r['error']:+.2f} %"
        lines.append(
            f"| {r['scheme']} | {r['mu']:g} | {r['d']:.5f} ({r['cells']:.1f} cells) | {r['exact']:.5f} | {err} "
            f"| {100 * r['of_frictionless']:.2f} % | {r['run_s']:.2f} | {r['jit_s']:.2f} | {r['status']} |")
    lines.append(
        f"\nslide: theta = 30°, g = 9.8, uGIMP, normal 'first', h = 0.025, 2x2 ppc, cfl 0.5, t_end = "
        f"{rows[0]['t_end']:.4g}; contact='coulomb' with friction μ.  Exact: g (sin θ − μ cos θ) t² / 2 "
        "while tan θ > μ (tan 30° = 0.577), else 0.  The last column is the displacement as a fraction of the "
        "frictionless exact one (the issue's criterion for μ = 0.7: below 1 %).  Undamped FLIP and XPIC creep at "
        "μ = 0.7: gravity switched on at t = 0 sets the elastic slab ringing, and the slab surface's oscillating "
        "velocity breaks the friction cone at most contact nodes every step, so the block ratchets down; PIC damps the "
        "ringing.  Under a quasi-static load (gravity raised over 0.05 s, 'ramp 0.05' rows; exact and "
        "frictionless columns for the ramped load) FLIP holds at μ = 0.7 and slides as it should at μ = 0, 0.2; "
        "particle damping α_p = 200 /s also stops the creep but stops the sliding block as well (μ = 0, 0.2 rows).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------- output
def thinned(n: int, rows: int) -> np.ndarray:
    """At most ``rows`` evenly spread indices of 0..n-1, the first and the last included."""
    return np.unique(np.linspace(0, n - 1, min(n, rows)).round().astype(int))


def write_disks_csv(path, runs, rows=201):
    """Energy histories, at most ``rows`` frames a run (every other frame of the full run's 400)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["scheme", "contact", "time", "total", "kinetic", "strain", "kinetic_0", "kinetic_1", "distance",
                    "contact_force_0_x", "contact_force_0_y"])
        for res in runs.values():
            h = res["h"]
            for i in thinned(h["time"].size, rows):
                w.writerow([res["label"], res["law"]] + [f"{h[k][i]:.10g}" for k in (
                    "time", "total", "kinetic", "strain", "kinetic_0", "kinetic_1", "distance")]
                    + [f"{c:.10g}" for c in h["force_0"][i]])


def write_rows_csv(path, rows, keys, series, max_rows=200):
    """One line per saved time of each run (at most ``max_rows``, evenly spread: the bars save every step)."""
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(keys + ["time"] + list(series))
        for r in rows:
            for i in thinned(r["time"].size, max_rows):
                w.writerow([r[k] for k in keys] + [f"{r['time'][i]:.10g}"] + [f"{r[s][i]:.10g}" for s in series])


def plot_disks(path, runs, labels):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, math.ceil(len(labels) / 2), figsize=(4 * math.ceil(len(labels) / 2), 6.5),
                             sharex=True, sharey=True, squeeze=False)
    for ax, label in zip(axes.flat, labels):
        for law in LAWS:
            res = runs.get((label, law))
            if res is None:
                continue
            h = res["h"]
            ax.plot(h["time"], h["total"] / h["total"][0], label=LAW_LABEL[law])
        ax.set_title(label)
        ax.set_ylim(0.0, 1.1)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(labels):]:
        ax.set_visible(False)
    axes[0, 0].legend(fontsize=8)
    for ax in axes[:, 0]:
        ax.set_ylabel("total energy / E0")
    for ax in axes[-1]:
        ax.set_xlabel("time")
    fig.suptitle("disks: total energy by contact law (float64, USL, uGIMP)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)



def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="a reduced smoke run (see the module docstring)")
    parser.add_argument("--out", type=Path, default=RESULTS, help="results folder")
    args = parser.parse_args(argv)
    quick = args.quick
    t_end = 3.0 if quick else 4.0
    t_compare = min(T_COMPARE, t_end)
    frames = 150 if quick else 400
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "contact_quick" if quick else "contact"
    started = time.perf_counter()
    md = [f"# Contact measurements ({'--quick' if quick else 'full'}; jax {jax.__version__} on "
          f"{jax.devices()[0].platform})\n"]

    # 1. disks
    runs, rows = {}, []
    schemes = disks_schemes(quick)
    for label, scheme in schemes.items():
        for law in LAWS:
            print(f"disks: {label}, {law} ...", flush=True)
            runs[(label, law)] = run_disks(label, scheme, law, t_end, frames)
            rows.append(summarise_disks(runs[(label, law)], t_end))
            r = rows[-1]
            print(f"  min E/E0 in contact {fmt(r['min_contact'])}, E(end)/E0 {fmt(r['after'])}, {r['status']}, "
                  f"run {r['run_s']:.2f} s, jit {r['jit_s']:.2f} s", flush=True)
    md += ["## disks: scheme x contact law\n", disks_table(rows, t_end), ""]

    # 2. stick vs one field: dedicated runs to t_compare, stick without the separation criterion (a
    #    perfect interface on every shared node, which is what single-field MPM does)
    pair = {}
    compare_schemes = dict(schemes)
    compare_schemes["FMPM(2)"] = jm.FMPM(order=2)
    for label, scheme in compare_schemes.items():
        for law in ("none", "stick"):
            print(f"disks: {label}, {law} (no separation criterion) to t = {t_compare:g} ...", flush=True)
            options = {} if law == "none" else {"separation": NO_SEPARATION}
            pair[(label, law)] = run_disks(label, scheme, law, t_compare, int(round(frames * t_compare / t_end)),
                                           **options)
    stick_rows = stick_vs_single(pair, t_compare)
    md += ["## disks: contact='stick' against one field (003 §3.3)\n", stick_table(stick_rows, t_compare), ""]

    # 3. bars_impact
    bar_rows = []
    cells_list = (32,) if quick else (32, 64, 128)
    for shape in ("linear",) if quick else ("linear", "ugimp"):
        for cells in cells_list:
            for label, scheme in {"FLIP": jm.FLIP(), "XPIC(2)": jm.XPIC(order=2), "FMPM(2)": jm.FMPM(order=2)}.items():
                for contact in ("frictionless", "none"):
                    print(f"bars_impact: {shape}, {label}, {contact}, {cells} cells ...", flush=True)
                    bar_rows.append(run_bars(label, scheme, contact, cells, shape))
        if shape == "ugimp":  # where the exchange reaches the 2 % (order ~0.75 in h)
            for label, scheme in {"FLIP": jm.FLIP(), "XPIC(2)": jm.XPIC(order=2), "FMPM(2)": jm.FMPM(order=2)}.items():
                print(f"bars_impact: {shape}, {label}, frictionless, 256 cells ...", flush=True)
                bar_rows.append(run_bars(label, scheme, "frictionless", 256, shape))
    md += ["## bars_impact: velocity exchange and contact duration\n", bars_table(bar_rows), ""]

    # 4. slide
    slide_rows = []
    slide_schemes = {"FLIP": jm.FLIP()} if quick else {"FLIP": jm.FLIP(), "PIC": jm.PIC(), "XPIC(2)": jm.XPIC(order=2)}
    for label, scheme in slide_schemes.items():
        for mu in ((0.0, 0.7) if quick else (0.0, 0.2, 0.7)):
            print(f"slide: {label}, mu = {mu} ...", flush=True)
            slide_rows.append(run_slide(label, scheme, mu))
    if not quick:  # FLIP's mu = 0.7 creep is the undamped slab's ringing: load quasi-statically, or damp it
        for mu in (0.0, 0.2, 0.7):
            print(f"slide: FLIP, gravity ramped over 0.05, mu = {mu} ...", flush=True)
            slide_rows.append(run_slide("FLIP, ramp 0.05", jm.FLIP(), mu, ramp=0.05))
        for mu in (0.0, 0.2, 0.7):
            print(f"slide: FLIP, alpha_p = 200, mu = {mu} ...", flush=True)
            slide_rows.append(run_slide("FLIP, α_p = 200", jm.FLIP(), mu, damping=jm.Damping(particle=200.0)))
    md += ["## slide: displacement against the exact one\n", slide_table(slide_rows), ""]

    md.append(f"Total wall time of `python experiments/contact.py{' --quick' if quick else ''}`: "
              f"{time.perf_counter() - started:.0f} s.")
    text = "\n".join(md)
    (args.out / f"{stem}.md").write_text(text + "\n")
    write_disks_csv(args.out / f"{stem}_disks.csv", runs)
    write_rows_csv(args.out / f"{stem}_bars.csv", bar_rows, ["shape", "scheme", "contact", "cells"],
                   ["v_left", "v_right"])
    write_rows_csv(args.out / f"{stem}_slide.csv", slide_rows, ["scheme", "mu"], ["displacement", "reference"])
    plot_disks(args.out / f"{stem}_disks.png", runs, list(schemes))
    print()
    print(text)
    print(f"\nwrote {args.out}/{stem}.md, {stem}_disks.csv, {stem}_bars.csv, {stem}_slide.csv, {stem}_disks.png")


if __name__ == "__main__":
    main()
