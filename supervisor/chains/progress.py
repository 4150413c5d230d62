"""Progress and ETA of a test, for the ``chN.chain.progress`` / ``chN.chain.eta_s`` tags."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class Progress:
    """Against an estimated duration when one is known (e.g. from a dry run), else, in a
    constant-current step, against the rated capacity (seed 001's progress bar: charge
    moved in this step over the capacity, ETA at the step's current)."""

    estimated_duration_s: float | None = None

    def update(
        self,
        *,
        active: bool,
        complete: bool,
        elapsed_s: float,
        step_current_a: float | None,
        step_moved_ah: float,
        capacity_ah: float | None,
    ) -> tuple[float, float | None] | None:
        """(progress 0…1, ETA in s or None), or None to leave the tags as they are.

        ``active``: a test is under way; ``complete``: it completed; ``step_current_a``:
        the current of the active CC step (None when the step is not one).
        """
        return self.shown(active, complete, elapsed_s, step_current_a, step_moved_ah, capacity_ah)

    def shown(
        self,
        active: bool,
        complete: bool,
        elapsed_s: float,
        step_current_a: float | None,
        step_moved_ah: float,
        capacity_ah: float | None,
    ) -> tuple[float, float | None] | None:
        """:meth:`update` with positional arguments (the chain calls it every scan)."""
        est = self.estimated_duration_s
        if active and est:
            return min(1.0, elapsed_s / est), max(0.0, est - elapsed_s)
        if active and step_current_a is not None and capacity_ah:
            moved = abs(step_moved_ah)
            amps = abs(step_current_a)
            eta = max(0.0, (capacity_ah - moved) * 3600.0 / amps) if amps > 0 else None
            return min(1.0, moved / capacity_ah), eta
        if complete:
            return 1.0, 0.0
        return None
