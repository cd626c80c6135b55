"""Unit file (ICD section 1): one flight unit's set of magnetometers.

The dataclasses here are the contract the rest of the toolchain uses; `load_unit`
reads and validates a TOML file into them.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from generator.io import parts as _parts

# Parts the toolchain knows: the catalogue generator/io/parts.toml (generator.io.parts),
# by name and alias. count_min/count_max: the raw output range of the part's default
# setting (None for "generic": from the unit file's range_nT); a reading at or beyond
# either end is saturated. SensorSpec.count_min/max give one sensor's range.
PARTS = {
    name: {"count_min": p.count_min, "count_max": p.count_max,
           "set_reset_capable": p.set_reset, "temperature": p.temperature,
           "range_nT": p.range_nT, "generic": p.generic}
    for name, p in _parts.catalogue().items()
}

FRAMES = ("body", "boom")
FLOAT_TYPES = ("float32", "float64")


@dataclass(frozen=True)
class SensorSpec:
    name: str                 # [a-z][a-z0-9_]*; telemetry column prefix
    part: str                 # a key of PARTS
    frame: str                # "body" or "boom"
    axes: tuple               # e.g. ("+z", "+y", "+x"): frame axes X, Y, Z are these sensor axes
    lsb_nT: float             # nT per count (input = "counts"; else not used, 1.0)
    zero_count: int           # count at zero field (input = "counts"; else not used, 0)
    set_reset: bool           # telemetry holds SET and RESET outputs
    noise_nT: float | None = None
    # ICD section 4 (version 2), all optional:
    input: str = "counts"     # what the <s>_x.. columns hold: counts | nT | uT | mG | G
    temperature: bool = True  # False: the sensor reports no temperature (no <s>_temp_C)
    range_nT: float | None = None  # full-scale field per axis ("generic" parts)

    @property
    def count_min(self) -> int:
        return self._count_range()[0]

    @property
    def count_max(self) -> int:
        return self._count_range()[1]

    def _count_range(self) -> tuple[int, int]:
        return _parts.count_range(_parts.part(self.part), self.lsb_nT, self.zero_count,
                                  self.range_nT)

    @property
    def counts(self) -> bool:
        """True: the <s>_x.. columns hold integer counts (ICD section 1); False: real
        numbers in a physical unit (ICD section 4)."""
        return self.input == "counts"

    @property
    def nT_per_input(self) -> float:
        """nT per unit of the <s>_x.. columns: lsb_nT for counts, else the unit's factor."""
        return float(self.lsb_nT) if self.counts else _parts.INPUT_UNITS_nT[self.input]

    @property
    def full_scale_nT(self) -> float:
        """Full-scale field per axis, nT: the unit file's range_nT, else the part's
        setting matched by lsb_nT, else the part's widest range."""
        return _parts.sensor_range_nT(_parts.part(self.part),
                                      self.lsb_nT if self.counts else None, self.range_nT)

    @property
    def count_columns(self) -> tuple:
        """Telemetry columns of raw counts (ICD section 2), in this order:
        SET/RESET: <s>_set_x, _set_y, _set_z, <s>_reset_x, _reset_y, _reset_z; else <s>_x, _y, _z."""
        if self.set_reset:
            return tuple(f"{self.name}_{kind}_{a}" for kind in ("set", "reset") for a in "xyz")
        return tuple(f"{self.name}_{a}" for a in "xyz")

    @property
    def temp_column(self) -> str:
        return f"{self.name}_temp_C"

    @property
    def required_columns(self) -> tuple:
        """Columns a telemetry file must hold for this sensor: the field (or count)
        columns, and <s>_temp_C unless temperature = false."""
        return (*self.count_columns, *((self.temp_column,) if self.temperature else ()))

    def axis_map(self) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
        """(index, sign): frame[k] = sign[k] * sensor[index[k]] (seed 000, eq. 1)."""
        idx = tuple("xyz".index(a[1]) for a in self.axes)
        sign = tuple(1 if a[0] == "+" else -1 for a in self.axes)
        return idx, sign  # type: ignore[return-value]


@dataclass(frozen=True)
class Unit:
    id: str
    sensors: tuple            # of SensorSpec, in file order
    lab_field_nT: float | None = None
    float_type: str = "float32"
    boom_reference: str | None = None   # body-frame sensor the boom sensors are aligned to
    path: str | None = None   # where it was read from (for messages)
    extra: dict = field(default_factory=dict, compare=False)  # unknown tables kept verbatim

    def sensor(self, name: str) -> SensorSpec:
        for s in self.sensors:
            if s.name == name:
                return s
        raise KeyError(name)

    @property
    def sensor_names(self) -> tuple:
        return tuple(s.name for s in self.sensors)

    def to_dict(self) -> dict:
        """Plain-data form, embedded in coefficients.json so `generate` needs no TOML."""
        return {
            "id": self.id,
            "lab_field_nT": self.lab_field_nT,
            "float": self.float_type,
            "boom_reference": self.boom_reference,
            "sensors": [
                {
                    "name": s.name, "part": s.part, "frame": s.frame, "axes": list(s.axes),
                    "lsb_nT": s.lsb_nT, "zero_count": s.zero_count,
                    "set_reset": s.set_reset, "noise_nT": s.noise_nT,
                    # version-2 keys only where they differ from version 1's meaning, so a
                    # version-1 unit's coefficients.json keeps its bytes
                    **({"input": s.input} if s.input != "counts" else {}),
                    **({"temperature": False} if not s.temperature else {}),
                    **({"range_nT": s.range_nT} if s.range_nT is not None else {}),
                }
                for s in self.sensors
            ],
        }

    @staticmethod
    def from_dict(d: dict) -> "Unit":
        return Unit(
            id=d["id"],
            lab_field_nT=d.get("lab_field_nT"),
            float_type=d.get("float", "float32"),
            boom_reference=d.get("boom_reference"),
            sensors=tuple(
                SensorSpec(
                    name=s["name"], part=s["part"], frame=s["frame"], axes=tuple(s["axes"]),
                    lsb_nT=float(s["lsb_nT"]), zero_count=int(s["zero_count"]),
                    set_reset=bool(s["set_reset"]), noise_nT=s.get("noise_nT"),
                    input=s.get("input", "counts"), temperature=s.get("temperature", True),
                    range_nT=s.get("range_nT"),
                )
                for s in d["sensors"]
            ),
        )
