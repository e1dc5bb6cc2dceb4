"""Object classes shared by every layer (wire code = enum value)."""

from enum import IntEnum


class ObjectClass(IntEnum):
    UNKNOWN = 0
    CAR = 1
    VAN = 2
    TRUCK = 3
    BUS = 4
    PEDESTRIAN = 5
    CYCLIST = 6
    MOTORCYCLE = 7

    @classmethod
    def parse(cls, name: "str | int | ObjectClass") -> "ObjectClass":
        """Accept an enum, its integer code or its case-insensitive name."""
        if isinstance(name, str):
            try:
                return cls[name.strip().upper()]
            except KeyError:
                raise ValueError(f"unknown object class {name!r}; one of {[c.name.lower() for c in cls]}") from None
        return cls(name)
