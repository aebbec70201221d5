"""Errors raised by jaxmpm, and the small helper that raises them."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: the message names the parameter and the fix."""


class InstabilityError(RuntimeError):
    """A run went unstable: the driver found a non-finite state, an inverted particle (det F <= 0)
    or a particle off the grid (``jaxmpm.run.driver``).  The arguments are kept as attributes.

    Args:
        step: the first bad step (an integer).
        cause: why, in words, with the first offending particle, e.g. "J = det F <= 0 (a particle
            inverted) (particle 12)".
        time: the simulated time of that step, or None (the default) when unknown.
        history: the frames saved before that step (a :class:`jaxmpm.History`), where the run kept
            them in memory; None (the default) where a writer holds them (in its file) or none was
            finished.
    """

    def __init__(self, step: int, cause: str, time: float | None = None, history=None):
        self.step = int(step)
        self.cause = cause
        self.time = time
        self.history = history
        when = f" (t = {time:.6g})" if time is not None else ""
        super().__init__(
            f"simulation went unstable at step {self.step}{when}: {cause}. "
            "Reduce dt (see jaxmpm.stable_dt) or use a smoother scheme/shape."
        )


class ParticlesLeftGrid(InstabilityError):
    """Particles left the grid: the motion outgrew the grid, not a numerical instability (the
    driver's cause 3).  An :class:`InstabilityError`, so code that catches those catches it too;
    the arguments are kept as attributes, ``cause`` says it in words ("particles left the grid
    (...)") and ``detail`` names the particle, its position and the grid's box.

    Args:
        step: the first step at which a particle's shape function reaches past the grid's nodes.
        particle: the first such particle.
        position: its position at ``step`` (D numbers), or None where unknown (a ``lax.scan``
            rollout goes on past the step).
        lower: the grid's lower corner, or None.
        upper: the grid's upper corner, or None.
        time: the simulated time of ``step``, or None.
        history: the frames saved before ``step``, as for :class:`InstabilityError`.
    """

    def __init__(self, step: int, particle: int, position=None, lower=None, upper=None, time: float | None = None,
                 history=None):
        self.history = history
        self.step = int(step)
        self.particle = int(particle)
        self.position = None if position is None else tuple(float(c) for c in position)
        self.lower = None if lower is None else tuple(float(c) for c in lower)
        self.upper = None if upper is None else tuple(float(c) for c in upper)
        self.time = time
        where = "" if self.position is None else f" at x = {_point(self.position)}"
        box = "" if self.lower is None else f"; the grid spans {_point(self.lower)} .. {_point(self.upper)}"
        self.detail = f"particle {self.particle}{where}, where its shape function reaches past the grid's nodes{box}"
        self.cause = f"particles left the grid ({self.detail})"
        when = f" (t = {time:.6g})" if time is not None else ""
        RuntimeError.__init__(
            self, f"run stopped at step {self.step}{when}: {self.cause}; the grid is too small for the motion (not "
                  "a numerical instability): enlarge it (e.g. jm.Grid.covering with room for the motion) or "
                  "shorten the run")


def _point(values) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in values) + ")"


def check(condition: bool, message: str) -> None:
    """Raise :class:`InputError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise InputError(message)
