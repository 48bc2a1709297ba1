"""Stable 4-byte J2735 temporary IDs for the members of a convoy.

A BSM names its sender only by a 4-byte ``TemporaryID``. Each convoy member keeps one ID
for the whole run (privacy-motivated ID rotation would break the convoy's bookkeeping, and
a research convoy on a closed track does not need it). By default the ID of vehicle ``i``
(0 = leader) is derived from the convoy's name, so every member computes the same table
without configuration; a lab can override any entry, e.g. to match a vehicle running
another J2735 stack.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator, Mapping

from openconvoy.core.errors import ConfigError


def derive_temp_id(convoy: str, index: int) -> bytes:
    """The default temporary ID of vehicle ``index`` in convoy ``convoy``: 4 bytes."""
    return hashlib.sha256(f"openconvoy/{convoy}/{index}".encode()).digest()[:4]


def parse_temp_id(value: bytes | str) -> bytes:
    """A temporary ID from 4 bytes or 8 hex digits (``"0A1B2C3D"``, optional ``0x``)."""
    if isinstance(value, str):
        text = value.strip().lower().removeprefix("0x")
        try:
            value = bytes.fromhex(text)
        except ValueError:
            raise ConfigError(f"temporary ID {text!r} is not hexadecimal") from None
    if len(value) != 4:
        raise ConfigError(f"temporary ID must be 4 bytes (8 hex digits), got {len(value)} bytes")
    return bytes(value)


class TempIds:
    """Two-way map between convoy vehicle index (0 = leader) and 4-byte temporary ID.

    Args:
        convoy: the convoy's name; all members must use the same one.
        size: number of vehicles in the convoy (indices 0..size-1).
        overrides: explicit IDs for some indices (bytes or hex strings).

    Raises ``ValueError`` if two vehicles would share an ID.
    """

    def __init__(
        self,
        convoy: str = "openconvoy",
        size: int = 16,
        overrides: Mapping[int, bytes | str] | None = None,
    ) -> None:
        if size < 1:
            raise ConfigError(f"convoy size must be at least 1, got {size}")
        self.convoy = convoy
        self._ids = [derive_temp_id(convoy, i) for i in range(size)]
        for index, value in (overrides or {}).items():
            if not 0 <= index < size:
                raise ConfigError(
                    f"temporary ID override for vehicle {index}: not in 0..{size - 1}"
                )
            self._ids[index] = parse_temp_id(value)
        self._index = {tid: i for i, tid in enumerate(self._ids)}
        if len(self._index) != size:
            dup = sorted({tid.hex() for tid in self._ids if self._ids.count(tid) > 1})
            raise ConfigError(f"temporary IDs collide within the convoy: {', '.join(dup)}")

    def __len__(self) -> int:
        return len(self._ids)

    def __iter__(self) -> Iterator[tuple[int, bytes]]:
        return iter(enumerate(self._ids))

    def id_of(self, index: int) -> bytes:
        """The temporary ID of vehicle ``index`` (``IndexError`` outside the convoy)."""
        if not 0 <= index < len(self._ids):
            raise IndexError(f"vehicle {index} is not in this convoy of {len(self._ids)}")
        return self._ids[index]

    def index_of(self, temp_id: bytes) -> int | None:
        """The vehicle index that owns ``temp_id``, or None for foreign traffic."""
        return self._index.get(temp_id)

    def __contains__(self, index: object) -> bool:
        return isinstance(index, int) and 0 <= index < len(self._ids)

    def __repr__(self) -> str:
        return f"TempIds(convoy={self.convoy!r}, ids={[t.hex() for t in self._ids]})"
