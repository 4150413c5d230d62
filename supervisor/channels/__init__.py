"""Channels: a source (Chadèche board, later an EA supply) bound to its tags.

A channel integrates charge and energy, takes operator setpoints in Manual mode,
clamps every request to its hard limits and trips safe on a limit or a lost input.
It sees tags only, never drivers.
"""

from supervisor.channels.channel import Channel, ChannelLimits, Mode

__all__ = ["Channel", "ChannelLimits", "Mode"]
