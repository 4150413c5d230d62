"""Importers: files from other tools turned into recipes (YAML text you review and keep).

* :func:`import_chadeche` — a Chadèche sequence file + ``chadecheN.prm`` (seed 000 §III.D);
* :func:`import_profile` — a load profile CSV (seed 002 §2.3) as one ``profile:`` step.
"""

from supervisor.importers.chadeche import ImportResult, import_chadeche
from supervisor.importers.profile import import_profile

__all__ = ["ImportResult", "import_chadeche", "import_profile"]
