"""Issue 20 item 1: `magcal trace` above its cap works on contiguous blocks of each file
drawn at random (generator.trace.subsample, MAX_TRACE_SAMPLES, `--max-samples`) and says
so; under the cap nothing changes.

Long files: the fast thermal campaign of test_trace (432 rows, 5 s) with a planted effect
(test_trace.make_case), repeated with fresh noise and glued in time behind a gap of an hour
(a chamber restarted: the temperature screen accepts any change across such a gap), so a
file is several blocks of MIN_BLOCK_ROWS rows; the cap is set below the file's rows.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from generator.io.telemetry import Telemetry
from generator.trace import subsample as sub
from generator.trace import tracer as tr

from test_trace import found_effects, make_case, run

PARTS = 12               # 12 x 432 = 5,184 rows: 6 blocks of 1,000 rows (the last shorter)
CAP = 2_500              # L = 1,000 (MIN_BLOCK_ROWS): one block in 3 kept, 2 of 6


def _json(res) -> dict:
    d = json.loads(json.dumps(res.to_json(), default=tr._json_default))
    d.pop("elapsed_s")
    return d


def long_file(case, out, name) -> Telemetry:
    """PARTS runs of the case's campaign (same truth and effects, fresh noise), one file."""
    tels = [run(case.kind, case.unit, case.truth, case.seed + i, out, case.effects,
                name=f"{name}_{i}")[0] for i in range(PARTS)]
    cols, t_end = {c: [] for c in tels[0].columns}, 0.0
    for t in tels:
        ts = np.asarray(t.time_s, float)
        shift = t_end - ts[0]
        for c in cols:
            cols[c].append(np.asarray(t.columns[c], float) + (shift if c == "time_s" else 0))
        t_end = float(ts[-1] + shift) + 3600.0
    cols = {c: np.concatenate(v) for c, v in cols.items()}
    n = len(cols["time_s"])
    return Telemetry(str(out / f"{name}.csv"), cols, np.arange(2, n + 2), dict(tels[0].meta))


@pytest.fixture(scope="module")
def planted(tmp_path_factory):
    out = tmp_path_factory.mktemp("sub_planted")
    case = make_case("channel_bias", 1, out)
    return case, long_file(case, out, "planted")


def _rows_seen(res) -> int:
    return max(t.S_fit.n + t.S_eval.n for t in res.traces.values())


def test_under_the_cap_nothing_changes(planted, tmp_path):
    case, tel = planted
    short = run(case.kind, case.unit, case.truth, case.seed, tmp_path, case.effects)[0]
    a = tr.trace(case.unit, [short])                      # default cap, far above 432 rows
    b = tr.trace(case.unit, [short], max_samples=0)       # no cap
    assert a.subsample is None and "subsample" not in _json(a)
    assert not any(n.startswith("subsample") for n in a.notes)
    assert _json(a) == _json(b)
    a.coefficients.save(tmp_path / "a.json")
    b.coefficients.save(tmp_path / "b.json")
    assert (tmp_path / "a.json").read_bytes() == (tmp_path / "b.json").read_bytes()
    # the same at a cap exactly at the rows
    c = tr.trace(case.unit, [short], max_samples=short.n)
    assert c.subsample is None and _json(c) == _json(a)


def test_capped_trace_says_so_is_bounded_deterministic_and_finds_the_effect(planted):
    case, tel = planted
    assert tel.n == PARTS * 432
    res = tr.trace(case.unit, [tel], max_samples=CAP)
    info = res.subsample
    L = sub.MIN_BLOCK_ROWS
    assert info["samples"] == tel.n and info["block_rows"] == L
    assert info["one_block_in"] == 3 and info["blocks"] == 2, info
    assert info["traced"] <= CAP
    # the rows trace works on are the kept blocks, not the file
    assert _rows_seen(res) <= info["traced"]
    d = _json(res)
    assert d["subsample"]["traced"] == info["traced"]
    assert any(n.startswith("subsample: ") and f"{tel.n:,} samples; traced on "
               f"{info['traced']:,} in {info['blocks']} blocks of {L:,}" in n for n in d["notes"])
    assert res.coefficients.fit_info["trace"]["subsample"] == info["text"]
    found = [(n, e, c) for n, e, c, _ in found_effects(res)]
    assert found == [(case.sensor, "channel_bias", [case.channel])], found
    # the apply over every row: all usable rows counted, the traced coefficients below
    # the baseline's where the effect was found, unchanged where nothing was added
    rows = d["subsample"]["all_rows"]
    assert set(rows) == set(res.traces)
    assert all(v["samples"] > info["traced"] for v in rows.values())
    assert rows[case.sensor]["traced_rms_nT"] < rows[case.sensor]["baseline_rms_nT"]
    for n, t in res.traces.items():
        if not t.steps:
            assert rows[n]["traced_rms_nT"] == rows[n]["baseline_rms_nT"]
    again = tr.trace(case.unit, [tel], max_samples=CAP)
    assert _json(again) == d


def test_capped_clean_long_file_invents_nothing(tmp_path):
    case = make_case("channel_bias", 2, tmp_path)
    case.effects = []                       # the same campaign, nothing planted
    tel = long_file(case, tmp_path, "clean")
    res = tr.trace(case.unit, [tel], max_samples=CAP)
    assert res.subsample is not None
    assert [(n, st.effect.label()) for n, st in res.effects] == []


def _runs(ts):
    """The runs of consecutive rows (time step 1) of a kept file: [(first, last)]."""
    cut = np.nonzero(np.diff(ts) != 1.0)[0] + 1
    return [(int(r[0]), int(r[-1])) for r in np.split(ts, cut)]


def test_blocks_are_contiguous_rows_of_one_file_and_seeded():
    n = 10_500
    t = Telemetry("f.csv", {"time_s": np.arange(n) * 1.0, "x": np.arange(n) * 2.0},
                  np.arange(2, n + 2))
    (a,), _, info = sub.subsample_files([t], [], 3_000)
    (b,), _, _ = sub.subsample_files([t], [], 3_000)
    # the kept blocks stay the file: the whole file (its rows bridge the lag recursions
    # across the gaps), its samples the drawn blocks' rows
    assert a.path == t.path and np.array_equal(a.sample_rows, b.sample_rows)
    assert a.columns is t.columns and a.n == t.n
    renamed = Telemetry("g.csv", t.columns, t.line_numbers)       # the draw is the rows'
    (c,), _, _ = sub.subsample_files([renamed], [], 3_000)
    assert np.array_equal(c.sample_rows, a.sample_rows)
    L = info["block_rows"]
    ts = a.time_s[a.sample_rows]
    runs = _runs(ts)
    assert len(runs) == info["blocks"] >= 2   # several blocks drawn: not vacuous
    for first, last in runs:                   # whole blocks of L rows, on the block grid
        assert first % L == 0 and (last - first + 1 == L or last == n - 1)
    assert int(a.sample_rows.sum()) == info["traced"] <= 3_000
    same, _, none = sub.subsample_files([t], [], 0)
    assert none is None and same == [t]


@pytest.mark.parametrize("value", ["-1", "x", "1.5"])
def test_bad_max_samples_exit_2_one_line(value, capsys):
    from generator.cli import main
    rc = main(["trace", "u.toml", "d.csv", "-o", "out", "--max-samples", value])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--max-samples" in err, err


@pytest.mark.parametrize("value", [-1, 1.5, True])
def test_bad_max_samples_in_the_api(planted, value):
    from generator.errors import InputError
    case, tel = planted
    with pytest.raises(InputError, match="max_samples"):
        tr.trace(case.unit, [tel], max_samples=value)


def test_all_rows_confirmation_vetoes_what_every_row_refutes(planted):
    """The blocks decide, all the rows may veto: the planted effect lowers the error over
    every row (kept), removing it again raises it (vetoed, said why)."""
    case, tel = planted
    res = tr.trace(case.unit, [tel], max_samples=CAP)
    st = res.traces[case.sensor].steps[0]
    S = res.traces[case.sensor].S_fit
    from generator.trace.samples import candidate_channels
    confirm = sub.all_rows_confirmation([tel], res.unit, coils=res.coefficients.spec.coils,
                                        H=None, channels=candidate_channels(res.unit, [tel])[0])
    assert confirm(case.sensor, st.model_before, st.model_after) == ""
    why = confirm(case.sensor, st.model_after, st.model_before)
    assert why.startswith(sub.CONFIRM_PREFIX) and f"{tel.n:,} usable samples" in why, why
    assert S.n < tel.n                        # the blocks are not every row: not vacuous


def test_an_effect_all_rows_refute_is_dropped_and_said(planted, monkeypatch):
    """A veto reaches trace.json: the effect is refused (per sensor) and named in the
    notes, and the coefficients carry no effect."""
    case, tel = planted

    def veto_all(*a, **k):
        return lambda name, m0, m1: f"{sub.CONFIRM_PREFIX}: vetoed by the test"
    monkeypatch.setattr(tr, "all_rows_confirmation", veto_all)
    res = tr.trace(case.unit, [tel], max_samples=CAP)
    assert res.effects == []
    d = _json(res)
    refused = [r for s in d["final"].values() for r in s.get("refused", [])]
    assert any(r["why"].startswith(sub.CONFIRM_PREFIX) for r in refused), d["final"]
    assert any(n.startswith("subsample: accepted on the blocks but dropped") and
               "channel_bias" in n for n in d["notes"]), d["notes"]


def test_an_effect_with_no_held_out_gain_is_refused(planted, monkeypatch):
    """One statistic: the held-out RMS shown must fall. A refit that changes nothing
    (as the real ecl_office log's channel_bias(armed) on per-block constants did:
    787.86 -> 787.86 nT) is refused, not kept at equality; with the cap or without."""
    case, tel = planted
    kept = tr.trace(case.unit, [tel], max_samples=CAP)
    assert [n for n, _ in kept.effects] == [case.sensor]    # found when it does lower it
    real = tr._refine_and_fit

    def no_change(model, S_fit, e, sc):
        real(model, S_fit, e, sc)                 # the effect's own set-up, then nothing
        return model.copy()
    monkeypatch.setattr(tr, "_refine_and_fit", no_change)
    for cap in (CAP, 0):
        res = tr.trace(case.unit, [tel], max_samples=cap)
        assert res.effects == []
        why = [w for t in res.traces.values() for _, w in t.rejected]
        assert any(w.startswith("the evaluation rows show no gain") for w in why), why
