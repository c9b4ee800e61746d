"""One check shared by every config dataclass: settings read from a file or a dict must all be known."""

from __future__ import annotations

from dataclasses import fields

from causalgs.errors import CausalGSError


def check_keys(cls, d: dict, what: str) -> None:
    """A one-line error naming the unknown keys of ``d`` for dataclass ``cls`` and listing the known ones."""
    known = {f.name for f in fields(cls) if f.init}
    unknown = sorted(set(d) - known)
    if unknown:
        raise CausalGSError(f"unknown {what} setting(s): {', '.join(unknown)} (settings: {', '.join(sorted(known))})")
