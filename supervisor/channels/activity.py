"""What a channel does, in words: the label of the Overview tile, the channel screen's
header and ``supervisor ctl status`` (issue 26: a channel driven at 20 A in Manual was shown
as "Idle manual", its step chain's state).

The channel's state (``chN.state``: ``idle``, ``charging``, ``discharging``, ``faulted``)
comes from the current it commands (``chN.current_cmd``), so the label takes that current:
``charging 20.000 A, manual``, ``discharging 0.200 A, auto``, ``idle, manual``. The step
chain's state (``chN.chain.state``) is shown beside it, as ``chain: Idle``, never in its
place. The screens write the same label (``hmi/js/screens/overview.js``, ``activityLabel``).
"""

from __future__ import annotations

MOVING = ("charging", "discharging")


def activity_label(state: object, current_cmd_a: object, mode: object) -> str:
    """``<channel state>[ <|commanded current|> A], <mode>``; ``—`` for a state not known."""
    text = "—" if state is None or state == "" else str(state)
    if text in MOVING and isinstance(current_cmd_a, int | float):
        text += f" {abs(current_cmd_a):.3f} A"
    if mode is not None and mode != "":
        text += f", {mode}"
    return text


def chain_label(state: object) -> str:
    """The step chain's state beside the channel's: ``chain: Idle``."""
    return f"chain: {'—' if state is None or state == '' else state}"
