"""The catalogue of magnetometer parts (generator/io/parts.toml), read once.

    part("IST8310")            # Part, by name or alias; InputError-free lookups: see find()
    find("MPU-9250")           # Part or None
    names()                    # canonical names, in file order
    count_range(part, lsb_nT, zero_count, range_nT)   # raw range of one sensor
    temperature_lsb_C("MMC5883MA")                    # 0.7: its temperature's step

The file is data: adding a part is adding a table there (keys documented at its top).
"""

from __future__ import annotations

try:
    import tomllib
except ImportError:                      # Python 3.10
    import tomli as tomllib
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

GENERIC = "generic"
INPUT_UNITS_nT = {"nT": 1.0, "uT": 1e3, "mG": 1e2, "G": 1e5}   # nT per unit of the column
INPUTS = ("counts", *INPUT_UNITS_nT)


@dataclass(frozen=True)
class Resolution:
    setting: str
    lsb_nT: float
    range_nT: float
    count_min: int | None = None      # None: the part's
    count_max: int | None = None
    zero_count: int | None = None     # None: the part's


@dataclass(frozen=True)
class Part:
    name: str
    maker: str
    datasheet: str
    aliases: tuple
    count_min: int | None             # None for generic (from the unit file's range)
    count_max: int | None
    zero_count: int | None
    range_nT: float                   # widest full scale per axis; 0 for generic
    set_reset: bool                   # SET/RESET capable
    temperature: bool                 # reports a temperature
    noise_nT: float | None            # typical 1-sigma per axis and reading
    noise_note: str = ""
    temp_lsb_C: float | None = None   # step of the reported temperature (None: not given)
    resolutions: tuple = ()
    generic: bool = False

    def resolution_for(self, lsb_nT) -> Resolution | None:
        """The setting whose lsb_nT is this one (to 0.1 %), or None."""
        for r in self.resolutions:
            if lsb_nT is not None and abs(r.lsb_nT - lsb_nT) <= 1e-3 * r.lsb_nT:
                return r
        return None


def _load() -> dict:
    text = resources.files("generator.io").joinpath("parts.toml").read_text(encoding="utf-8")
    doc = tomllib.loads(text)
    out = {}
    for name, d in doc.items():
        res = tuple(Resolution(setting=r["setting"], lsb_nT=float(r["lsb_nT"]),
                               range_nT=float(r["range_nT"]), count_min=r.get("count_min"),
                               count_max=r.get("count_max"), zero_count=r.get("zero_count"))
                    for r in d.get("resolution", ()))
        out[name] = Part(name=name, maker=d["maker"], datasheet=d["datasheet"],
                         aliases=tuple(d.get("aliases", ())), count_min=d.get("count_min"),
                         count_max=d.get("count_max"), zero_count=d.get("zero_count"),
                         range_nT=float(d["range_nT"]), set_reset=bool(d["set_reset"]),
                         temperature=bool(d["temperature"]), noise_nT=d.get("noise_nT"),
                         noise_note=d.get("noise_note", ""), resolutions=res,
                         temp_lsb_C=(float(d["temp_lsb_C"]) if "temp_lsb_C" in d else None),
                         generic=bool(d.get("generic", False)))
    return out


@lru_cache(maxsize=1)
def catalogue() -> dict:
    """{name or alias: Part}; canonical names first, in file order."""
    parts = _load()
    out = dict(parts)
    for p in parts.values():
        for a in p.aliases:
            out[a] = p
    return out


def names() -> tuple:
    """Canonical part names, in the catalogue's order."""
    return tuple(dict.fromkeys(p.name for p in catalogue().values()))


def find(name) -> Part | None:
    return catalogue().get(name) if isinstance(name, str) else None


def part(name) -> Part:
    p = find(name)
    if p is None:
        raise KeyError(f"unknown part {name!r}; known parts: {known_text()}")
    return p


def temperature_lsb_C(name) -> float | None:
    """The step of a part's reported temperature (degC), None when the catalogue gives
    none or the part is unknown; for find_segments(temp_lsb_C=...)."""
    p = find(name)
    return p.temp_lsb_C if p is not None else None


def known_text() -> str:
    """'MMC5883MA, MMC5983MA, MPU-9255 (MPU-9250, AK8963), ...' for messages."""
    return ", ".join(p.name + (f" ({', '.join(p.aliases)})" if p.aliases else "")
                     for p in (catalogue()[n] for n in names()))


def count_range(p: Part, lsb_nT, zero_count, range_nT=None) -> tuple[int, int]:
    """Raw count range of one sensor: the setting's (matched by lsb_nT), else the part's;
    generic parts: zero_count -+ range_nT / lsb_nT, rounded outwards."""
    if p.generic:
        if not range_nT or not lsb_nT:
            raise ValueError("generic part: range_nT and lsb_nT are needed for a count range")
        half = -(-float(range_nT) // float(lsb_nT))          # ceil
        return int(zero_count - half), int(zero_count + half)
    r = p.resolution_for(lsb_nT)
    if r is not None and r.count_min is not None:
        return int(r.count_min), int(r.count_max)
    return int(p.count_min), int(p.count_max)


def sensor_range_nT(p: Part, lsb_nT=None, range_nT=None) -> float:
    """Full-scale field per axis of one sensor, nT: the unit file's range_nT where given,
    else the setting matched by lsb_nT, else the part's widest range."""
    if range_nT:
        return float(range_nT)
    r = p.resolution_for(lsb_nT)
    return float(r.range_nT if r is not None else p.range_nT)
