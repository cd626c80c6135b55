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



def read_telemetry(path, unit, *, require_sensors: bool = True) -> "Telemetry":
    """Read and validate one telemetry CSV against the unit (ICD section 2).

    Raises InputError (file, line, column, fault) on: unreadable file, no header, missing
    `time_s`, a sensor column the unit requires missing (require_sensors), a cell that is
    not a number, a literal NaN/inf cell, time going backwards, a row with the wrong
    number of cells, a count outside the part's raw range. Empty cells are missing values
    (NaN) and are allowed. Extra columns are kept as channels.
    """
    from generator.io.telemetry_csv import read_csv
    return read_csv(path, unit, require_sensors=require_sensors)


def preprocess(tel: "Telemetry", unit) -> dict:
    """Counts -> nT, SET/RESET -> field and chip offset, axis mapping -> frame axes.

    Per sensor: usable=False where any needed cell is missing or non-finite, or a count is at
    the part's rail (saturated); these are counted in n_missing / n_saturated, never used.
    """
    from generator.io.telemetry_csv import preprocess_sensors
    return preprocess_sensors(tel, unit)
