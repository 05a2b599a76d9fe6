"""lodcast's error hierarchy: every error is a LodcastError and also the built-in it resembles."""
from __future__ import annotations

__all__ = [
    "LodcastError",
    "SourceNotFound",
    "SourceError",
    "StoreNotFound",
    "StoreExists",
    "StoreInvalid",
    "StoreCorrupt",
]


class LodcastError(Exception):
    """Base of every error lodcast raises on purpose (bad input, missing things)."""


class SourceNotFound(LodcastError, FileNotFoundError):
    """The volume to ingest does not exist."""


class SourceError(LodcastError, ValueError):
    """The volume to ingest exists but cannot be used (format, shape, dtype, content)."""


class StoreNotFound(LodcastError, FileNotFoundError):
    """No lodcast store at this path."""


class StoreExists(LodcastError, FileExistsError):
    """The ingest destination exists and overwriting was not asked for."""


class StoreInvalid(LodcastError, ValueError):
    """A path holds something that is not a complete lodcast store."""


class StoreCorrupt(StoreInvalid):
    """A lodcast store whose data files are missing or damaged since ingest wrote them (re-ingest it)."""
