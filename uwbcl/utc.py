"""ISO 8601 UTC times, the one parser and formatter every layer uses (archive attributes, outputs,
Modbus TIME)."""

from __future__ import annotations

import datetime as dt


def parse_utc(text: str) -> dt.datetime:
    """An aware UTC datetime from ISO 8601 text ending in 'Z' or '+00:00'; ValueError naming the text
    otherwise."""
    # Python 3.10's fromisoformat does not take "Z"; spell it as an offset first.
    s = text[:-1] + "+00:00" if text.endswith(("Z", "z")) else text
    try:
        t = dt.datetime.fromisoformat(s)
    except (TypeError, ValueError):
        raise ValueError(f"not an ISO 8601 date-time: {text!r}") from None
    if t.utcoffset() != dt.timedelta(0):
        raise ValueError(f"must be UTC ('Z' or '+00:00'), got {text!r}")
    return t


def utc_seconds(text: str | None) -> float:
    """Seconds since 1970-01-01T00:00:00Z of an ISO 8601 UTC time (0.0 for none or empty)."""
    return parse_utc(text).timestamp() if text else 0.0


def time_order(text: str) -> tuple[float, str]:
    """Sort key of an ISO 8601 UTC time: the instant, then the text. As text, '...:00.500Z' sorts before
    '...:00Z' and '+00:00' before 'Z'; ValueError for text that is no UTC time."""
    return utc_seconds(text), text


def format_utc(epoch_s: float) -> str:
    """'YYYY-MM-DDTHH:MM:SS.mmmZ' for seconds since 1970 (rounded to the millisecond)."""
    t = dt.datetime.fromtimestamp(round(epoch_s, 3), tz=dt.timezone.utc)
    return t.strftime("%Y-%m-%dT%H:%M:%S.") + f"{t.microsecond // 1000:03d}Z"
