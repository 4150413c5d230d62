"""The logic phases of one scan, in the order docs/design.md "One scan" gives them.

1. derived values (copied measurements, power, Ah/Wh), so that everything after sees this
   scan's values;
2. safety (interlocks, alarms), before any step chain, so no recipe can override it;
3. the step chains, which read tags and request setpoints;
4. outputs: each channel selects, protects and clamps its setpoint into the output tags.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from supervisor.scan.engine import LogicPhase


@dataclass(frozen=True)
class ScanPhases:
    derived: Sequence[LogicPhase] = ()
    safety: Sequence[LogicPhase] = ()
    chains: Sequence[LogicPhase] = ()
    outputs: Sequence[LogicPhase] = ()

    def ordered(self) -> list[LogicPhase]:
        return [*self.derived, *self.safety, *self.chains, *self.outputs]
