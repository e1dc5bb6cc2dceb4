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


# Class-typical box sizes l, w, h (m): a monocular detector reports the class prior size
# (Saravanan et al. Sec. I: 3D-Net / CAROM take dimensions from the recognised vehicle type).
CLASS_DEFAULT_LWH: dict[ObjectClass, tuple[float, float, float]] = {
    ObjectClass.UNKNOWN: (4.0, 1.8, 1.6),
    ObjectClass.CAR: (4.6, 1.85, 1.5),
    ObjectClass.VAN: (5.9, 2.0, 2.6),
    ObjectClass.TRUCK: (8.0, 2.5, 3.5),
    ObjectClass.BUS: (12.0, 2.55, 3.2),
    ObjectClass.PEDESTRIAN: (0.6, 0.6, 1.75),
    ObjectClass.CYCLIST: (1.8, 0.6, 1.7),
    ObjectClass.MOTORCYCLE: (2.2, 0.8, 1.5),
}
