"""Errors raised by jaxmpm, and the small helper that raises them."""

from __future__ import annotations


class InputError(ValueError):
    """Bad input: the message names the parameter and the fix."""


class InstabilityError(RuntimeError):
    """A run went unstable.  ``step`` is the first bad step, ``cause`` says why."""

    def __init__(self, step: int, cause: str, time: float | None = None):
        self.step = int(step)
        self.cause = cause
        self.time = time
        when = f" (t = {time:.6g})" if time is not None else ""
        super().__init__(
            f"simulation went unstable at step {self.step}{when}: {cause}. "
            "Reduce dt (see jaxmpm.stable_dt), use a smoother scheme/shape, or enlarge the grid."
        )


def check(condition: bool, message: str) -> None:
    """Raise :class:`InputError` with ``message`` unless ``condition`` holds."""
    if not condition:
        raise InputError(message)
