"""Reproducible creation times for the written PDF/DXF files (the SOURCE_DATE_EPOCH convention of
reproducible-builds.org): the time ``SOURCE_DATE_EPOCH`` names, else a fixed one, never the clock."""
from __future__ import annotations

import datetime
import os
import re

FIXED_TIME = datetime.datetime(2000, 1, 1, tzinfo=datetime.timezone.utc)
"""Creation time written when SOURCE_DATE_EPOCH is not set."""


def source_date() -> datetime.datetime:
    """UTC creation time to write: SOURCE_DATE_EPOCH (seconds since 1970) when set to an integer, else
    ``FIXED_TIME``."""
    value = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if value.isdigit():
        return datetime.datetime.fromtimestamp(int(value), tz=datetime.timezone.utc)
    return FIXED_TIME


def with_pdf_creation_date(pdf: bytes, when: datetime.datetime) -> bytes:
    """``pdf`` with its ``/CreationDate (D:YYYYMMDDHHMMSS...)`` set to ``when`` (UTC); the new value
    has the old one's length, so the cross-reference offsets stay valid."""
    stamp = when.astimezone(datetime.timezone.utc).strftime("%Y%m%d%H%M%S").encode()

    def replace(match: re.Match) -> bytes:
        old = match.group(1)
        new = (stamp + b"Z")[: len(old)] if len(old) >= 15 else old
        return b"/CreationDate (D:" + new.ljust(len(old), b" ") + b")"

    return re.sub(rb"/CreationDate \(D:([^)]*)\)", replace, pdf)
