"""Telemetry CSV (ICD section 2) and preprocessing to uncalibrated frame-axis fields.

Contract used by the fitters, `apply`, `trace` and the simulator's writer:

    tel = read_telemetry(path, unit)        # validates; raises InputError
    tel.columns["mmc1_set_x"]               # float64 array, NaN where the cell was empty
    tel.time_s                              # float64 array, non-decreasing
    data = preprocess(tel, unit)            # {sensor name: SensorData}
    data["mmc1"].field_frame_nT             # (N, 3) float64, SET/RESET'd and axis-mapped
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Telemetry:
    path: str
    columns: dict                      # name -> float64 ndarray (N,), file column order kept
    line_numbers: np.ndarray           # 1-based file line of each sample, for messages
    meta: dict = field(default_factory=dict)  # '# key: value' comment lines
    comments: list = field(default_factory=list)  # other comment lines, verbatim

    @property
    def n(self) -> int:
        return int(self.line_numbers.shape[0])

    @property
    def time_s(self) -> np.ndarray:
        return self.columns["time_s"]

    def has(self, *names) -> bool:
        return all(n in self.columns for n in names)

    def get(self, name, default=None):
        return self.columns.get(name, default)


@dataclass
class SensorData:
    name: str
    field_frame_nT: np.ndarray         # (N, 3) raw field in frame axes (not calibrated), float64
    temp_C: np.ndarray                 # (N,) reported sensor temperature
    usable: np.ndarray                 # (N,) bool: False where missing, saturated or non-finite
    n_missing: int = 0
    n_saturated: int = 0
    chip_offset_sensor_nT: np.ndarray | None = None  # (N, 3) SET/RESET sensors: (set+reset)/2 - zero, sensor axes
    counts: dict = field(default_factory=dict)        # raw count columns used, by column name
    missing_columns: tuple = ()        # needed columns absent from the file (require_sensors=False)
    has_temperature: bool = True       # False (temperature = false): temp_C is all NaN

    def temp_or(self, fill_C: float) -> np.ndarray:
        """The reported temperature; for a sensor without one (has_temperature False), the
        constant fill_C: the temperature-independent model's stand-in, never a reading."""
        if self.has_temperature:
            return self.temp_C
        return np.full_like(np.asarray(self.temp_C, dtype=np.float64), float(fill_C))
