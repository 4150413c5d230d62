"""Tag database: declared signals whose values always travel with quality and time."""

from supervisor.tags.db import Tag, TagDB
from supervisor.tags.spec import Access, AlarmLimits, HistorySettings, Scaling, TagSpec

__all__ = ["Access", "AlarmLimits", "HistorySettings", "Scaling", "Tag", "TagDB", "TagSpec"]
