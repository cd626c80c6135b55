"""Issue 20 item 1: above a per-sensor cap the fit takes a systematic random subsample
(generator.fit.samples._gather, MAX_FIT_SAMPLES, `magcal fit --max-samples N`) and says
so; under the cap nothing changes."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from generator.cli import main
from generator.errors import InputError
from generator.fit.samples import (MAX_FIT_SAMPLES, _gather, subsample_rng,
                                   subsample_step, systematic_sample)
from generator.fit.thermal import fit_data_from, fit_sensor
from generator.io.telemetry_csv import preprocess, read_telemetry
from generator.io.unitfile import load_unit
from generator.pipeline import fit

CAP = 3000          # the thermal campaign has 36,000 usable samples per sensor: k = 12


def _fit_bytes(fm1_dir, tmp_path, tag, max_samples, files=("thermal_12pos.csv",)):
    cs = fit(fm1_dir / "unit.toml", [fm1_dir / f for f in files], max_samples=max_samples)
    path = tmp_path / f"{tag}.json"
    cs.save(path)
    return path.read_bytes()


@pytest.fixture(scope="module")
def fits(fm1_dir, tmp_path_factory):
    """coefficients.json bytes of the thermal campaign: default cap, no cap, a cap equal
    to the usable count (k = 1), and CAP twice."""
    tmp = tmp_path_factory.mktemp("subsample")
    return {tag: _fit_bytes(fm1_dir, tmp, tag, m) for tag, m in
            (("default", None), ("all", 0), ("at_count", 36000), ("cap", CAP),
             ("cap_again", CAP))}


@pytest.fixture(scope="module")
def fm1_datas(fm1_dir):
    """FitData of mmc1 in the thermal campaign and the rotation campaign."""
    unit = load_unit(fm1_dir / "unit.toml")
    out = []
    for f in ("thermal_12pos.csv", "rotation.csv"):
        tel = read_telemetry(fm1_dir / f, unit)
        out.append(fit_data_from(tel, preprocess(tel, unit)["mmc1"], unit))
    return out


def _stats(raw, sensor):
    return json.loads(raw)["fit"]["sensors"][sensor]["stats"]


def test_under_the_cap_nothing_changes(fits):
    # the default cap (200,000) and a cap equal to the usable count keep every sample:
    # the same bytes as no cap at all, and nothing in the stats says otherwise
    assert fits["default"] == fits["all"] == fits["at_count"]
    for sensor, v in json.loads(fits["default"])["fit"]["sensors"].items():
        st_ = v["stats"]
        assert "all_samples_residual_nT" not in st_
        assert all("fit_samples" not in f for f in st_["files"])
        assert not any("usable samples; the fit used" in n for n in st_["notes"])


def test_capped_fit_says_so_and_is_deterministic(fits):
    assert fits["cap"] == fits["cap_again"]          # the seed is fixed
    assert fits["cap"] != fits["all"]
    for sensor, v in json.loads(fits["cap"])["fit"]["sensors"].items():
        st_ = v["stats"]
        (f,) = st_["files"]
        k = math.ceil(f["used"] / CAP)
        assert f["used"] == 36000 and k == 12
        assert f["fit_samples"] == math.ceil(f["used"] / k) == st_["samples_used"]
        note = [n for n in st_["notes"] if "usable samples; the fit used" in n]
        assert len(note) == 1
        assert f"sensor '{sensor}': 36,000 usable samples; the fit used 3,000" in note[0]
        assert "block of 12 consecutive samples" in note[0]
        assert "its sigmas are those of 3,000 samples" in note[0]


def test_capped_coefficients_agree_with_the_full_fit(fits):
    """theta_sub - theta_full: the full fit's samples contain the subsample's, so for a
    least-squares estimate var(theta_sub - theta_full) = sigma_sub^2 - sigma_full^2 <
    sigma_sub^2: each difference over sigma_sub is at most a standard normal. The bound
    is the two-sided normal quantile of a family-wise false alarm of 1e-3 over all the
    data-determined coefficients compared (Bonferroni; correlated coefficients only make
    it more conservative): 4.6 sigma for 240."""
    from scipy.stats import norm

    z = []
    for sensor in json.loads(fits["all"])["fit"]["sensors"]:
        full, sub = _stats(fits["all"], sensor), _stats(fits["cap"], sensor)
        # the same temperature model chosen (the comparison is of one model's estimates)
        assert (sub["chosen"], sub["degree"]) == (full["chosen"], full["degree"]), sensor
        fv = {p["name"]: p["value"] for p in full["observability"]["parameters"]}
        for p in sub["observability"]["parameters"]:
            if p["source"] == "data":
                z.append((abs(p["value"] - fv[p["name"]]) / p["sigma"], sensor, p["name"]))
    assert len(z) >= 200
    bound = norm.isf(1e-3 / (2 * len(z)))
    assert max(z)[0] < bound, (bound, sorted(z)[-3:])


def test_all_samples_residual_is_close_to_the_fit_residual(fits):
    """The residual over all 36,000 usable samples (33,000 never seen by the fit) against
    the fit's own on its 3,000: at the noise level the residuals are near-Gaussian, the
    relative 1-sigma of an RMS over n_eq = 3 n equations is 1 / sqrt(2 n_eq), and the fit
    lowers its own residual's square by p / n_eq (p = 48 coefficients of a cubic). Bound:
    4 such sigmas plus p / n_eq."""
    for sensor in json.loads(fits["cap"])["fit"]["sensors"]:
        st_ = _stats(fits["cap"], sensor)
        alls, own = st_["all_samples_residual_nT"], st_["fit"]
        assert alls["n"] == 36000 and alls["n_not_in_fit"] == 33000 and own["n"] == 3000
        n_eq = 3 * own["n"]
        tol = 4.0 / math.sqrt(2 * n_eq) + 48 / n_eq
        ratio = alls["rms_vector_nT"] / own["rms_vector_nT"]
        assert abs(ratio - 1) < tol, (sensor, ratio, tol)
        assert any("over all 36,000 usable samples (33,000 not in the fit)" in n
                   for n in st_["notes"])


def test_two_files_subsampled_per_file_with_segments_remapped(fm1_datas):
    """Two files (36,000 + 4,000 usable): k = ceil(40,000 / 3,000) = 14 in each file, and
    every segment found on the full files keeps exactly the subsample's samples that lie
    in it."""
    notes_all, files_all = [], []
    S_all = _gather("mmc1", fm1_datas, notes_all, files_all, 0)
    notes, files, said = [], [], []
    S = _gather("mmc1", fm1_datas, notes, files, CAP, said.append)
    k = subsample_step(sum(f["used"] for f in files), CAP)
    assert k == 14
    assert [f["fit_samples"] for f in files] == [math.ceil(f["used"] / k) for f in files]
    assert S.n == sum(f["fit_samples"] for f in files) <= CAP + len(files)
    assert said == [n for n in notes if "usable samples" in n] and len(said) == 1
    assert "40,000 usable samples; the fit used 2,858" in said[0]
    # the subsample is a subset of the usable samples, in time order within each file
    for fid in range(2):
        t_sub = S.time_s[S.file_id == fid]
        t_all = S_all.time_s[S_all.file_id == fid]
        assert np.all(np.diff(t_sub) > 0) and np.isin(t_sub, t_all).all()
    # segments: found on the full files (same number), each keeps the samples drawn in it
    assert len(S.segments) == len(S_all.segments) > 10
    for s_sub, s_all in zip(S.segments, S_all.segments):
        fid = S_all.file_id[s_all.index[0]]
        members = np.isin(S.time_s, S_all.time_s[s_all.index]) & (S.file_id == fid)
        assert np.array_equal(np.sort(s_sub.index), np.nonzero(members)[0])
        assert (s_sub.temp_C, s_sub.t_start_s) == (s_all.temp_C, s_all.t_start_s)
        # one sample per block: at least one from each block wholly inside the segment,
        # at most one from each block it touches
        start = np.searchsorted(S_all.file_id, fid)
        m = int(np.sum(S_all.file_id == fid))
        blocks = (s_all.index - start) // k
        size = np.minimum(k, m - np.unique(blocks) * k)
        inside = np.bincount(blocks)[np.unique(blocks)]
        assert np.sum(inside == size) <= len(s_sub.index) <= len(size)


@pytest.mark.parametrize("method", ["ellipsoid", "analytic"])
def test_per_level_methods_run_on_the_subsample(fm1_datas, method):
    cal = fit_sensor("mmc1", fm1_datas[:1], method=method, max_samples=CAP)
    lf = cal.stats["segments"]["level_fits"]
    assert cal.stats["method"] == method and len(lf) >= 2
    assert sum(level["samples"] for level in lf) <= CAP
    assert cal.stats["files"][0]["fit_samples"] == CAP
    assert "all_samples_residual_nT" in cal.stats


def test_segments_left_nearly_empty_behave_as_short_segments(fm1_datas):
    """A cap of 100 (k = 360: one sample in 30 min) leaves segments of 10 min with 0 or 1
    sample: empty ones are dropped, the rest go to the level fits, which drop what they
    cannot fit, as for any too-short segment; nothing crashes."""
    S = _gather("mmc1", fm1_datas[:1], [], [], 100)
    assert S.n == 100 and all(len(s.index) >= 1 for s in S.segments)
    for method in ("auto", "analytic", "ellipsoid"):
        try:
            cal = fit_sensor("mmc1", fm1_datas[:1], method=method, max_samples=100)
        except InputError:      # a fit the 100 samples cannot determine: exit 2, one line
            continue
        assert cal.stats["samples_used"] == 100


@pytest.mark.parametrize("value", ["-1", "abc", "1.5", "", "1e5"])
def test_bad_max_samples_exit_2_one_line(fm1_dir, tmp_path, capsys, value):
    out = tmp_path / "f"
    rc = main(["fit", str(fm1_dir / "unit.toml"), str(fm1_dir / "rotation.csv"), "-o",
               str(out), "--no-report", "--max-samples", value])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "--max-samples" in err, err
    assert not out.exists()


@pytest.mark.parametrize("value", [-1, 2.5, "100", True])
def test_bad_max_samples_in_the_api(fm1_dir, value):
    with pytest.raises(InputError, match="max_samples"):
        fit(fm1_dir / "unit.toml", [fm1_dir / "rotation.csv"], max_samples=value)


def test_help_names_the_cap():
    from generator.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "verb")
    text = sub.choices["fit"].format_help()
    assert f"{MAX_FIT_SAMPLES}" in " ".join(text.split())


@settings(max_examples=200, deadline=None)
@given(n=st.integers(1, 5000), k=st.integers(1, 400), seed=st.integers(0, 3))
def test_systematic_sample_one_per_block(n, k, seed):
    pos = systematic_sample(n, k, subsample_rng(f"s{seed}", seed))
    blocks = np.arange(0, n, k)
    assert len(pos) == len(blocks) == math.ceil(n / k)
    assert np.all(pos >= blocks) and np.all(pos < np.minimum(blocks + k, n))
    assert np.array_equal(pos, systematic_sample(n, k, subsample_rng(f"s{seed}", seed)))


def test_subsample_draws_are_uniform_within_blocks():
    """Each position of a block is drawn with probability 1/k: over 20,000 blocks of 8 the
    counts per offset are binomial(20,000, 1/8), sd 46.8; all within 5 sd of 2,500."""
    pos = systematic_sample(160000, 8, subsample_rng("mmc1", 0))
    counts = np.bincount(pos % 8, minlength=8)
    sd = math.sqrt(20000 * (1 / 8) * (7 / 8))
    assert np.all(np.abs(counts - 2500) < 5 * sd), counts
    # another sensor or file draws differently (the seed includes the name and index)
    assert not np.array_equal(pos, systematic_sample(160000, 8, subsample_rng("mmc2", 0)))
    assert not np.array_equal(pos, systematic_sample(160000, 8, subsample_rng("mmc1", 1)))


def test_subsampled_fit_sigmas_are_honest_over_seeds(tmp_path_factory):
    """The subsample's stated 1-sigma against the truth, over 20 simulated draws (the
    chamber campaign of test_truth_chi2, 4,320 samples a sensor, capped at 2,000: one
    sample in each block of 3): sum z^2 per coefficient inside the chi-square interval of
    test_truth_chi2 (its statistics and false-alarm probability). A sigma that did not
    grow with the subsample would make the sums too large; one that grew beyond it, too
    small."""
    from generator.campaign import simulate as sim
    from test_truth_chi2 import CAMPAIGNS, SEEDS, _b, _M, z_scores

    base = tmp_path_factory.mktemp("chi2sub")
    draws = []
    for seed in SEEDS:
        out = base / str(seed)
        out.mkdir()
        unit = sim.make_example_unit(f"sub{seed}")
        truth = sim.random_truth(unit, np.random.default_rng(seed))
        sim.write_unit_toml(unit, out / "unit.toml")
        (kind, opt), = [c for c in CAMPAIGNS if c[0] == "thermal_12pos"]
        path, _ = sim.simulate_campaign(kind, unit, truth, np.random.default_rng(1000 * seed),
                                        out, **opt)
        cs = fit(out / "unit.toml", [path], max_samples=2000)
        files = cs.fit_info["sensors"]["mmc1"]["stats"]["files"]
        assert files[0]["used"] == 4320 and files[0]["fit_samples"] == 1440
        draws.append(z_scores(cs, truth.to_json()))
    _b(draws)
    _M(draws)


def test_magnitude_only_all_samples_residual(fm1_datas):
    """A file without reference vectors in the fit (the rotation campaign's magnitudes,
    through the ellipsoid method): the all-samples figure is the |B| RMS, over every
    usable sample, beside the fit's own."""
    rot = fm1_datas[1]
    cal = fit_sensor("mmc1", [rot], method="ellipsoid", max_samples=1000)
    alls, own = cal.stats["all_samples_residual_nT"], cal.stats["fit"]
    used = cal.stats["files"][0]["used"]
    assert alls["n"] == used and alls["n_not_in_fit"] == used - own["n"] > 0
    assert alls["rms_vector_nT"] is None and alls["rms_norm_nT"] > 0
    # the same bound as for the vectors, on n magnitude equations and the 9 parameters of
    # a constant ellipsoid (the rotation campaign is at one temperature)
    tol = 4.0 / math.sqrt(2 * own["n"]) + 9 / own["n"]
    assert abs(alls["rms_norm_nT"] / own["rms_norm_nT"] - 1) < tol
    assert any("|B| RMS over all" in n for n in cal.stats["notes"])


def test_level_windows_name_their_file_when_subsampled(fm1_datas):
    """Two files, above the cap: each level's windows are attributed to the file they come
    from (the file offsets count the subsample's samples, not the usable ones)."""
    two = [fm1_datas[0], fm1_datas[0]]
    full = fit_sensor("mmc1", two, method="ellipsoid", max_samples=0)
    capped = fit_sensor("mmc1", two, method="ellipsoid", max_samples=6000)
    for cal in (full, capped):
        files = {w[0] for lev in cal.stats["segments"]["level_fits"] for w in lev["windows_s"]}
        assert files == {0, 1}, files
