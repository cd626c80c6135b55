"""The samples a trace works on: per sensor, every usable reading with a field reference
of some kind (ICD section 2: what is known about the true field decides the residual
type), in time order, with the channels, coil currents and body rates that may explain
what is left; and the contiguous time blocks of the cross-validation.

Residual rows per sample:
* `ref_x/y/z_nT` present: vector rows B_cal - B_ref (3 per sample);
* else `ref_norm_nT` (or the unit's `lab_field_nT`): magnitude rows |B_cal| - |B|;
* else a static position (`position` > 0): B_cal - B_p, B_p an unknown constant per
  (file, position), fitted with the rest.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from generator.fit.reference import T_REF_C

VEC, NORM, POS = 0, 1, 2
KIND_NAMES = {VEC: "vector rows B_cal - B_ref (per axis)",
              NORM: "magnitude rows |B_cal| - |B|",
              POS: "deviation from a constant per static position (per axis)"}

N_BLOCKS = 50             # contiguous time blocks over a sensor's data


@dataclass
class FileSeries:
    """One file's temperature series of one sensor (all its readings, in time order):
    what the thermal-lag recursion runs over; and the candidate channels on the same
    rows (what a lagged channel's recursion runs over)."""
    name: str
    time_s: np.ndarray
    temp_C: np.ndarray
    channels: dict = field(default_factory=dict)


class _Unpacked(Mapping):
    """A PackedSeries' channels: each unpacked (and its rows selected) when asked for."""

    def __init__(self, owner):
        self._owner = owner

    def __getitem__(self, c):
        return self._owner._rows_of(self._owner._packed_channels[c])

    def __iter__(self):
        return iter(self._owner._packed_channels)

    def __len__(self):
        return len(self._owner._packed_channels)


class PackedSeries(FileSeries):
    """A FileSeries of a file held packed (trace.filerows.FileRows): its time, temperature
    and channels are PackedColumns over every row of the file, unpacked (and the series'
    rows taken, mask) each time they are read; the same values as FileSeries' arrays,
    without holding them (8 B a row each) for the whole trace."""

    def __init__(self, name, time, temp, channels: dict, mask=None):
        self.name = name
        self._packed = (time, temp)
        self._packed_channels = channels
        self._mask = mask

    def _rows_of(self, col):
        v = col.values()
        return v if self._mask is None else v[self._mask]

    time_s = property(lambda self: self._rows_of(self._packed[0]))
    temp_C = property(lambda self: self._rows_of(self._packed[1]))
    channels = property(lambda self: _Unpacked(self))


@dataclass
class SensorSamples:
    """The usable samples of one sensor with a field reference of some kind."""
    spec: object
    time_s: np.ndarray
    file_index: np.ndarray
    file_row: np.ndarray          # index into files[file_index].time_s
    order: np.ndarray             # global time order (files in the order given)
    x: np.ndarray                 # (n, 3) raw field, frame axes, nT
    temp_C: np.ndarray            # reported temperature
    kind: np.ndarray              # VEC / NORM / POS
    ref: np.ndarray               # (n, 3) reference vector (body frame), NaN where none
    norm: np.ndarray              # (n,) reference magnitude, NaN where none
    group: np.ndarray             # (n,) static-position id (file * 1e6 + position), -1
    ref_rate: np.ndarray          # (n, 2, 3) forward / backward slope of the reference, nT/s
    coil: np.ndarray | None       # (n, ncoil) modelled coil currents
    rate_frame_dps: np.ndarray | None   # (n, 3) body rate in the sensor's frame
    channels: dict                # candidate channel -> (n,), 0 where the file lacks it
    files: list                   # FileSeries per file index
    file_names: list
    role: np.ndarray              # 0 data file, 1 holdout file
    channel_present: dict = field(default_factory=dict)   # channel -> (n,) file has it
    block: np.ndarray | None = None
    _rows: tuple | None = None

    @property
    def n(self) -> int:
        return len(self.time_s)

    def subset(self, mask) -> "SensorSamples":
        m = np.asarray(mask)
        return SensorSamples(
            self.spec, self.time_s[m], self.file_index[m], self.file_row[m], self.order[m],
            self.x[m], self.temp_C[m], self.kind[m], self.ref[m], self.norm[m], self.group[m],
            self.ref_rate[m], None if self.coil is None else self.coil[m],
            None if self.rate_frame_dps is None else self.rate_frame_dps[m],
            {k: v[m] for k, v in self.channels.items()}, self.files, self.file_names,
            self.role[m], {k: v[m] for k, v in self.channel_present.items()},
            None if self.block is None else self.block[m])

    @property
    def idx(self):
        """(vector, magnitude, position) sample indices."""
        if self._rows is None:
            iv = np.nonzero(self.kind == VEC)[0]
            im = np.nonzero(self.kind == NORM)[0]
            ip = np.nonzero(self.kind == POS)[0]
            row_sample = np.concatenate([np.repeat(iv, 3), im, np.repeat(ip, 3)])
            row_axis = np.concatenate([np.tile([0, 1, 2], len(iv)), np.full(len(im), 3),
                                       np.tile([0, 1, 2], len(ip))])
            self._rows = (iv, im, ip, row_sample, row_axis)
        return self._rows[:3]

    @property
    def row_sample(self):
        self.idx
        return self._rows[3]

    @property
    def row_axis(self):
        """0, 1, 2 for the axis rows, 3 for magnitude rows."""
        self.idx
        return self._rows[4]

    @property
    def n_rows(self) -> int:
        return len(self.row_sample)

    def kinds_present(self) -> list:
        return [k for k in (VEC, NORM, POS) if np.any(self.kind == k)]


def candidate_channels(unit, tels, coils=()) -> tuple:
    """Columns that may explain a residual: numeric columns of the data files that are
    not time, position, sensor (<s>_...), reference (ref_...) or modelled coil columns.
    Returns (all names in first-seen order, the names only some files carry)."""
    prefixes = tuple(f"{s.name}_" for s in unit.sensors) + ("ref_",)
    skip = {"time_s", "position", *coils}
    # a sensor without temperature: the other sensors' temperature columns (a board it
    # shares) are its candidates (gather_samples gives them to such sensors only)
    temps = board_temperatures(unit)
    per = [[c for c in t.columns if c not in skip and (c in temps or not c.startswith(prefixes))]
           for t in tels]
    if not per:
        return [], []
    names = list(dict.fromkeys(c for cols in per for c in cols))
    partial = [c for c in names if not all(c in cols for cols in per)]
    return names, partial


def board_temperatures(unit) -> set:
    """The temperature columns of the unit's sensors that report one, where another
    sensor reports none (those become its candidate channels); else empty."""
    if all(s.temperature for s in unit.sensors):
        return set()
    return {s.temp_column for s in unit.sensors if s.temperature}


def _ref_rate(time_s, ref, position):
    """Slopes of the reference vectors to the next and from the previous reference
    sample, (n, 2, 3) nT/s, within runs of moving samples (position 0 or absent): the
    reference linearly interpolated a time dt later is ref + dt * slope (forward slope
    for dt > 0, backward for dt < 0). Zero in static positions and at the ends of runs."""
    out = np.zeros((len(ref), 2, 3))
    fin = np.isfinite(ref).all(axis=1)
    idx = np.nonzero(fin)[0]
    if len(idx) < 3:
        return out
    t = time_s[idx]
    pos = position[idx]
    dt = np.diff(t)
    med = np.median(dt[dt > 0]) if np.any(dt > 0) else 1.0
    brk = np.concatenate([[True], (pos[1:] != pos[:-1]) | (dt > 10 * med) | (dt <= 0)])
    run = np.cumsum(brk)
    for r in np.unique(run):
        sel = idx[run == r]
        if len(sel) < 3 or position[sel[0]] > 0:
            continue
        slope = np.diff(ref[sel], axis=0) / np.diff(time_s[sel])[:, None]
        out[sel[:-1], 0] = slope
        out[sel[1:], 1] = slope
    return out


def _held(v):
    """v with every non-finite cell replaced by the last finite value before it (0 before
    the first): a channel that stops being logged for a while (a telemetry dropout, a
    blank cell) keeps its value, as an importer holds a channel between its log entries
    (io.px4_ulog). Taken as 0 instead, a bus voltage at 8 V read 0 V through the dropout,
    and the lag recursions carried that into the rows after it (review #20c N1: 300 blank
    cells in rows a capped trace left out turned the right lagged bias into a wrong one,
    2x the truth's error)."""
    fin = np.isfinite(v)
    last = np.maximum.accumulate(np.where(fin, np.arange(len(v)), -1))
    return np.where(last >= 0, v[np.maximum(last, 0)], 0.0)


def _series_of(series, t, temp_C, chs, shared):
    """(time, temperature, channels) of the rows in series: the arrays themselves where
    every row is in it (no copy), else copies; the time and channels of one mask are
    copied once for all the sensors that share it (shared: [(mask, t, {channel: v})])."""
    if series.all():
        return t, temp_C, dict(chs)
    for m, ts, cs in shared:
        if np.array_equal(m, series):
            break
    else:
        ts, cs = t[series], {}
        shared.append((series, ts, cs))
    out = {}
    for c, v in chs.items():
        if c not in cs:
            cs[c] = v[series]
        out[c] = cs[c]
    return ts, temp_C[series], out


def gather_samples(unit, tels, roles, *, coils=(), H=None, channels=(), notes=None,
                   strict=(), sensors=None) -> dict:
    """{sensor: SensorSamples} over all files (data files then holdout files: the time
    order). roles: 0 data / 1 holdout per file. coils: the modelled coil columns; H: the
    boom -> body rotation (the rate in a boom sensor's frame is H^T w). strict: channels
    whose non-finite rows are missing (the samples left out: a user regressor's division
    by zero); other channels' empty cells are held at the channel's last value (_held).
    sensors: the names of the sensors to gather (default: all the unit's)."""
    from generator.io.telemetry_csv import preprocess, usable_rows
    from generator.trace.filerows import pack
    notes = notes if notes is not None else []
    specs = [s for s in unit.sensors if sensors is None or s.name in sensors]
    H = np.eye(3) if H is None else np.asarray(H, float)
    acc = {s.name: [] for s in specs}
    files = {s.name: [] for s in specs}
    names = [str(t.path) for t in tels]
    has_rate = any(all(f"rate_{a}_dps" in t.columns for a in "xyz") for t in tels)
    order0 = 0
    for fi, (tel, role) in enumerate(zip(tels, roles)):
        # the rows that may become samples (a capped trace's drawn blocks, else every row):
        # everything a sample carries is computed on them alone; the per-file series the
        # recursions run over (time, temperatures, channels, usable) on every row
        # (sample_view / full_column: trace.subsample's BlockedTelemetry and BlockedRows)
        rows = (None if getattr(tel, "sample_rows", None) is None
                else np.flatnonzero(tel.sample_rows))
        sub = tel if rows is None else tel.sample_view()
        full = getattr(tel, "full_column", tel.get)          # a column over every row
        pre = preprocess(sub, unit, sensors)
        n, ns = tel.n, sub.n
        t = np.asarray(tel.time_s, float)
        pos = sub.get("position")
        pos = np.zeros(ns) if pos is None else np.nan_to_num(np.asarray(pos, float))
        ref = (np.stack([sub.columns[f"ref_{a}_nT"] for a in "xyz"], axis=1).astype(float)
               if sub.has("ref_x_nT", "ref_y_nT", "ref_z_nT") else np.full((ns, 3), np.nan))
        has_vec = np.isfinite(ref).all(axis=1)
        if not has_vec.any():
            ref_rate = np.zeros((ns, 2, 3))
        elif rows is None:
            ref_rate = _ref_rate(t, ref, pos)
        else:                # the slopes run to the neighbours: over every row of the file
            pos_all = full("position")
            pos_all = np.zeros(n) if pos_all is None else np.nan_to_num(np.asarray(pos_all,
                                                                                  float))
            ref_rate = _ref_rate(t, np.stack([full(f"ref_{a}_nT") for a in "xyz"],
                                             axis=1).astype(float), pos_all)[rows]
        norm = sub.get("ref_norm_nT")
        norm = np.full(ns, np.nan) if norm is None else np.asarray(norm, float)
        if unit.lab_field_nT is not None and "ref_norm_nT" not in tel.columns:
            norm = np.full(ns, float(unit.lab_field_nT))
        has_norm = np.isfinite(norm) & (norm > 0)
        kind = np.where(has_vec, VEC, np.where(has_norm, NORM, np.where(pos > 0, POS, -1)))
        coil = None
        if coils:
            cols = [np.asarray(sub.columns[c], float) if c in sub.columns else np.zeros(ns)
                    for c in coils]
            coil = np.stack(cols, axis=1)
        rate = None
        if has_rate:
            if all(f"rate_{a}_dps" in sub.columns for a in "xyz"):
                rate = np.nan_to_num(np.stack([sub.columns[f"rate_{a}_dps"] for a in "xyz"],
                                              axis=1).astype(float))
            else:
                rate = np.zeros((ns, 3))
        # a file held packed (trace.filerows): its series stay packed (PackedSeries)
        packed = getattr(tel, "packed_column", None) if rows is not None else None
        chp = {}
        ch, present = {}, {}
        missing = np.zeros(n, bool)
        for c in channels:
            v = full(c)
            present[c] = v is not None
            if packed is not None and v is not None:
                chp[c] = packed(c)
            if v is None:
                v = np.zeros(n)
            v = np.asarray(v, float)
            if not np.isfinite(v).all():
                chp.pop(c, None)                 # packed below as changed
                bad = ~np.isfinite(v)
                if c in strict:
                    missing |= bad
                    notes.append(f"{tel.path}: channel {c} is not finite in "
                                 f"{int(bad.sum())} rows: those samples are missing")
                    v = np.nan_to_num(v)
                else:
                    notes.append(f"{tel.path}: channel {c} has {int(bad.sum())} "
                                 "empty cells, held at the channel's last value (0 before "
                                 "its first)")
                    v = _held(v)
            if packed is None:
                ch[c] = v
            else:            # held packed for the series; the samples' rows alone here
                if c not in chp:
                    chp[c] = pack(v)
                ch[c] = v[rows]
            del v
        temps = board_temperatures(unit)
        shared = []            # (series mask, its time and channels): one copy per mask
        for s in specs:
            sd = pre[s.name]
            # a sensor with its own temperature does not take the boards' as channels
            chs = {c: v for c, v in ch.items() if not (s.temperature and c in temps)}
            # a sensor without temperature (temperature = false): the constant stand-in
            # (its baseline clamps every temperature to dT = 0, so the value is immaterial)
            temp_C = np.asarray(sd.temp_or(T_REF_C), float)
            if rows is None:
                series = sd.usable & np.isfinite(temp_C)
                temp_all = temp_C
            else:
                usable = (tel.usable_of(s) if hasattr(tel, "usable_of")
                          else usable_rows(tel, s))
                col = full(s.temp_column) if s.temperature else None
                temp_all = (np.full(n, float(T_REF_C)) if not s.temperature else
                            np.full(n, np.nan) if col is None else np.asarray(col, float))
                series = usable & np.isfinite(temp_all)
            ok = (series if rows is None else series[rows]) & \
                np.isfinite(sd.field_frame_nT).all(axis=1) & (kind >= 0) & \
                ~(missing if rows is None else missing[rows])
            if coil is not None:
                ok &= np.isfinite(coil).all(axis=1)
            srow = np.cumsum(series) - 1
            if packed is None:
                files[s.name].append(FileSeries(names[fi], *_series_of(series, t, temp_all,
                                                                       chs, shared)))
            else:
                tp = (packed(s.temp_column) if s.temperature and
                      packed(s.temp_column) is not None else pack(temp_all))
                files[s.name].append(PackedSeries(
                    names[fi], packed("time_s"), tp, {c: chp[c] for c in chs},
                    None if series.all() else series))
            j = np.nonzero(ok)[0]                # among the sample rows
            i = j if rows is None else rows[j]   # among the file's rows
            w = None
            if rate is not None:
                w = rate[j] @ H if s.frame == "boom" else rate[j]
            acc[s.name].append(dict(
                time_s=t[i], file_index=np.full(len(i), fi), file_row=srow[i],
                order=order0 + i, x=sd.field_frame_nT[j], temp_C=temp_C[j],
                kind=kind[j], ref=ref[j], norm=np.where(has_vec[j], np.linalg.norm(
                    np.nan_to_num(ref[j]), axis=1), norm[j]),
                group=np.where(kind[j] == POS, fi * 1_000_000 + pos[j], -1).astype(np.int64),
                ref_rate=ref_rate[j], coil=None if coil is None else coil[j], rate=w,
                channels={c: v[i if packed is None else j] for c, v in chs.items()},
                role=np.full(len(i), role),
                present={c: np.full(len(i), present[c]) for c in chs}))
        del pre
        order0 += n
    out = {}
    for s in specs:
        parts = acc[s.name]

        def cat(key, parts=parts):
            vals = [p[key] for p in parts]
            return None if vals[0] is None else np.concatenate(vals)
        out[s.name] = SensorSamples(
            s, cat("time_s"), cat("file_index"), cat("file_row"), cat("order"), cat("x"),
            cat("temp_C"), cat("kind"), cat("ref"), cat("norm"), cat("group"),
            cat("ref_rate"), cat("coil"), cat("rate"),
            {c: np.concatenate([p["channels"][c] for p in parts]) for c in parts[0]["channels"]},
            files[s.name], names, cat("role"),
            {c: np.concatenate([p["present"][c] for p in parts]) for c in parts[0]["present"]})
    return out


def assign_blocks(S: SensorSamples, n_blocks=N_BLOCKS) -> np.ndarray:
    """Contiguous time blocks (sample order), cut at file changes and, for position
    rows, at position changes; a static position gets at least two blocks so that its
    constant is fitted from another block than the one held out."""
    n = S.n
    if n == 0:
        return np.zeros(0, int)
    o = np.argsort(S.order, kind="stable")
    key = S.file_index[o] * 10_000_000 + np.where(S.kind[o] == POS, S.group[o] % 1_000_000, -1)
    cut = np.concatenate([[0], np.nonzero(np.diff(key))[0] + 1, [n]])
    L = max(1.0, n / n_blocks)
    block = np.empty(n, int)
    b = 0
    for a, z in zip(cut[:-1], cut[1:]):
        m = z - a
        nb = max(1, int(round(m / L)))
        if S.kind[o[a]] == POS and m >= 2:
            nb = max(nb, 2)
        for chunk in np.array_split(np.arange(a, z), nb):
            block[o[chunk]] = b
            b += 1
    return block
