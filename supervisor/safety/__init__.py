"""Safety: the scan phase that runs after derived values and before the step chains.

Interlocks, alarms and feedback monitoring register here as checks (the safety issue fills
it); running before the chains and owning their own outputs, no recipe can override them.
"""

from supervisor.safety.phase import SafetyCheck, SafetyPhase

__all__ = ["SafetyCheck", "SafetyPhase"]
