"""Chadèche charger/discharger boards on one SPI bus (seed 000)."""

from supervisor.drivers.chadeche.bus import (
    BoardClaim,
    ChadecheBus,
    SpidevBus,
    board_lock_path,
    claim_board,
    default_lock_dir,
)
from supervisor.drivers.chadeche.driver import RELAY_SETTLE_S, ChadecheDriver

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
