"""Chadèche charger/discharger boards on one SPI bus (seed 000)."""

from supervisor.devices.chadeche.bus import (
    BoardClaim,
    ChadecheBus,
    SpidevBus,
    board_lock_path,
    claim_board,
    default_lock_dir,
)
from supervisor.devices.chadeche.driver import RELAY_SETTLE_S, ChadecheDriver

__all__ = [
    "RELAY_SETTLE_S",
    "BoardClaim",
    "ChadecheBus",
    "ChadecheDriver",
    "SpidevBus",
    "board_lock_path",
    "claim_board",
    "default_lock_dir",
]
