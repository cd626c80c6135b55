"""The curated mutations: deliberate bugs, one at a time, each with the tests that must
catch it.

A mutation is a list of edits (file, old text, new text). The old text is a SMALL,
DISTINCTIVE snippet of the current code (one condition, one assignment), so unrelated
edits around it do not break it; it must occur exactly once (the runner also accepts it
with different whitespace: re-indented or re-wrapped code still matches). A mutation
whose snippet no longer occurs once is reported NOT-APPLIED, which fails the check: the
code moved, and the edit must be re-targeted (keep the BUG, described in `what`, and find
the snippet that now implements the rule). Check every anchor without running tests:

    python3 bench/mutation/run.py --check

Edits planted in the C template and the Python reference alike are defined once each
below (CLAMP_UPPER_C, CLAMP_UPPER_PY, ...) and combined, so a re-target is one place.
Flight mutations change the template and the Python reference alike where the bug would
be planted in both; generated/ is never regenerated and test_generated.py (the byte
diff) is never run, so a kill comes from a behavioural test.
"""

from __future__ import annotations

from dataclasses import dataclass

EXPECT = ["host_tests/test_expectations.py"]
FLIGHT = EXPECT + ["host_tests/test_flight_chain.py", "host_tests/test_flight_bound.py",
                   "host_tests/test_prepare.py"]
CHI2 = ["host_tests/test_truth_chi2.py"]
FIT = ["host_tests/test_fit_accuracy.py"] + CHI2    # the tightened ratio test first
TRACE = ["host_tests/test_trace_decoys.py"]
TABLES = ["host_tests/test_tables.py"]
CHAIN = "generator/flight/chain.py"
TPL = "templates/magcal.c.j2"
REF = "generator/fit/reference.py"        # reference_fit: chamber (reference-vector) fits
JOINT = "generator/fit/joint.py"          # _joint_nonlinear: vectors + magnitudes
SCORING = "generator/trace/scoring.py"    # Score.judge, score_round
PRE = "generator/io/telemetry_csv.py"     # _sensor_data: counts -> nT, ICD axis mapping


@dataclass(frozen=True)
class Mutation:
    id: str
    what: str
    edits: tuple          # ((file, old, new), ...)
    tests: tuple


# ---- edits planted in both implementations (defined once, combined below) -------------
# the temperature clamp (wrapper): C `if (T < t_min) {...} else if (T > t_max) {...}`;
# Python `below, above = t < t_min, t > t_max` then the flags from below/above/far
_C = "c[{{ UNIT }}_{{ s.NAME }}_"
CLAMP_UPPER_C = (TPL, "} else if (temp_C > " + _C + "T_MAX_C]) {", "} else if (0) {")
CLAMP_UPPER_PY = (CHAIN, "below, above = t < t_min, t > t_max",
                  "below, above = t < t_min, t > np.inf")
CLAMP_LOWER_C = (TPL, "if (temp_C < " + _C + "T_MIN_C]) {", "if (0) {")
CLAMP_LOWER_PY = (CHAIN, "below, above = t < t_min, t > t_max",
                  "below, above = t < -np.inf, t > t_max")
# beyond the margin at the upper end: TEMP_CLAMPED (invalid) not set
CLAMP_UPPER_FAR_C = (TPL, "if (temp_C - " + _C + "T_MAX_C] > " + _C + "TEMP_MARGIN_C]) {",
                     "if (0) {")
CLAMP_UPPER_FAR_PY = (CHAIN, "(above & ((t - t_max).astype(ft) > margin))", "(above & False)")
# the margin ignored at the upper end: every sample above t_max invalid
MARGIN_UPPER_C = (TPL, "if (temp_C - " + _C + "T_MAX_C] > " + _C + "TEMP_MARGIN_C]) {",
                  "if (temp_C - " + _C + "T_MAX_C] > 0.0f) {")
MARGIN_UPPER_PY = (CHAIN, "(above & ((t - t_max).astype(ft) > margin))",
                   "(above & ((t - t_max).astype(ft) > 0))")
# the selection's majority rule: disagrees when it agrees with FEWER THAN half
MAJORITY_C = (TPL, "n_cmp[i] >= 2u && 2u * n_agree[i] < n_cmp[i]",
              "n_cmp[i] >= 2u && 2u * n_agree[i] <= n_cmp[i]")
MAJORITY_PY = (CHAIN, "n_cmp[i] >= 2 and 2 * n_agree[i] < n_cmp[i]",
               "n_cmp[i] >= 2 and 2 * n_agree[i] <= n_cmp[i]")
# the thermal lag on a backward clock step: holds (dt = 0), mutated to step with |dt|
LAG_C = (TPL, "dt_s = 0;   /* time going backwards (a clock step): hold the filter */",
         "dt_s = -dt_s;   /* time going backwards (a clock step): hold the filter */")
LAG_PY = (CHAIN, "dts = np.where(dts >= 0, dts, ft(0)).astype(ft)",
          "dts = np.abs(dts).astype(ft)")

# the chain's maths. The kernels (CasADi's C and the reference alike) are
# chain.folded_sensor_kernel: one edit there changes both. The constants folded once per
# table are chain.fold_sensor_coeffs (the reference's prepare_sensor, and the compiled-in
# prepared defaults) and, written a second time, `<unit>_table_prepare` in the C template:
# a bug in the fold is planted in both.
KERNEL_OFFSET_ADDED = (CHAIN, "x = [v[i] - b[i] for i in range(3)]",
                       "x = [v[i] + b[i] for i in range(3)]")
KERNEL_COIL_ADDED = (CHAIN, "x = [x[i] - coil[i] for i in range(3)]",
                     "x = [x[i] + coil[i] for i in range(3)]")
# the axis signs live in the fold's per-axis scale sig[k] (a negative sign negates it)
_SIG = 'sig[{{ k }}] = {{ "-" if f.sign[k] < 0 else "" }}'
AXIS_SIGN_C = tuple((TPL, _SIG + rest, "sig[{{ k }}] = " + rest) for rest in (
    "{{ f.scale_literal }};", "(c[{{ C }}LSB_NT] * ({{ R }})0.5);", "c[{{ C }}LSB_NT];"))
AXIS_SIGN_PY = (CHAIN, "return [scale if sign[k] > 0 else -scale for k in range(3)]",
                "return [scale for k in range(3)]")
# a counting SET/RESET pair's scale: lsb x 0.5 (the difference of the pair halved)
SR_HALF_C = (TPL, "(c[{{ C }}LSB_NT] * ({{ R }})0.5);", "(c[{{ C }}LSB_NT]);")
SR_HALF_PY = (CHAIN, 'scale = c.scalar("lsb_nT") * half if pair else c.scalar("lsb_nT")',
              'scale = c.scalar("lsb_nT") if pair else c.scalar("lsb_nT")')
# the kernel's dT = T - p[t_ref_C]: the prepared t_ref_C taken from the table's t_min_C
T_REF_C = (TPL, "p[{{ f.at.t_ref_C }}] = c[{{ C }}T_REF_C];",
           "p[{{ f.at.t_ref_C }}] = c[{{ C }}T_MIN_C];")
T_REF_PY = (CHAIN, 'f["t_ref_C"] = c.scalar("t_ref_C")', 'f["t_ref_C"] = c.scalar("t_min_C")')
# the boom rotation: folded into M (H M) by the prepare, or, for a boom sensor with the
# SET/RESET rate compensation (between M and H), applied by the kernel
H_FOLD_C = (TPL, "h[3 * i] * m[j] + h[3 * i + 1] * m[3 + j] + h[3 * i + 2] * m[6 + j]",
            "h[i] * m[j] + h[3 + i] * m[3 + j] + h[6 + i] * m[6 + j]")
H_FOLD_PY = (CHAIN, "M = [[[_dot3(H[i], [M[k][0][j], M[k][1][j], M[k][2][j]]) for j in range(3)]",
             "M = [[[_dot3([H[0][i], H[1][i], H[2][i]], [M[k][0][j], M[k][1][j], M[k][2][j]])"
             " for j in range(3)]")
H_KERNEL = (CHAIN, 'B = [_dot3(f["H"][i], B) for i in range(3)]',
            'B = [_dot3([f["H"][0][i], f["H"][1][i], f["H"][2][i]], B) for i in range(3)]')
# the band's field_max^2, squared once by the prepare
BAND_MAX_C = (TPL, "u[{{ UNIT }}_UNIT_FIELD_MAX_NT] * u[{{ UNIT }}_UNIT_FIELD_MAX_NT];",
              "u[{{ UNIT }}_UNIT_FIELD_MAX_NT] * 1000;")
BAND_MAX_PY = (CHAIN, 'f["field_min2"], f["field_max2"] = f_min * f_min, f_max * f_max',
               'f["field_min2"], f["field_max2"] = f_min * f_min, f_max * 1000')

M = Mutation
MUTATIONS = [
    # ---- the four bugs of issue 21 ----------------------------------------------------
    M("clamp_upper_removed", "upper temperature clamp removed (C and Python): above t_max "
      "the polynomials extrapolate, nothing flagged", (CLAMP_UPPER_C, CLAMP_UPPER_PY),
      tuple(EXPECT)),
    M("majority_at_most_half", "selection: 'fewer than half' -> 'at most half' (C and Python)",
      (MAJORITY_C, MAJORITY_PY), tuple(EXPECT)),
    M("lag_abs_dt", "thermal lag steps with |dt| on a backward clock step (C and Python)",
      (LAG_C, LAG_PY), tuple(EXPECT)),
    M("trace_no_bonferroni", "trace: the multiple-comparison factor dropped (every score "
      "judged as if alone in its round)",
      ((SCORING, "s.judge(len(scores), alpha, min_gain)", "s.judge(1, alpha, min_gain)"),),
      tuple(TRACE)),
    # ---- the same three flight bugs in one implementation only (C or Python) ----------
    M("clamp_upper_removed_C", "upper temperature clamp removed in the C only",
      (CLAMP_UPPER_C,), tuple(EXPECT)),
    M("clamp_upper_removed_py", "upper temperature clamp removed in the Python only",
      (CLAMP_UPPER_PY,), tuple(EXPECT)),
    M("majority_at_most_half_C", "'at most half' in the C only", (MAJORITY_C,), tuple(EXPECT)),
    M("majority_at_most_half_py", "'at most half' in the Python only", (MAJORITY_PY,),
      tuple(EXPECT)),
    M("lag_abs_dt_C", "|dt| on a backward step in the C only", (LAG_C,), tuple(EXPECT)),
    M("lag_abs_dt_py", "|dt| on a backward step in the Python only", (LAG_PY,), tuple(EXPECT)),
    # ---- wrappers -------------------------------------------------------------------
    M("clamp_lower_removed", "lower temperature clamp removed (C and Python)",
      (CLAMP_LOWER_C, CLAMP_LOWER_PY), tuple(EXPECT)),
    M("clamp_upper_unflagged", "upper clamp applied but a sample beyond the margin not "
      "flagged TEMP_CLAMPED, it stays valid (C and Python)",
      (CLAMP_UPPER_FAR_C, CLAMP_UPPER_FAR_PY), tuple(EXPECT)),
    M("clamp_upper_margin_ignored", "upper end: the margin ignored, every extrapolated "
      "sample flagged TEMP_CLAMPED (C and Python)", (MARGIN_UPPER_C, MARGIN_UPPER_PY),
      tuple(EXPECT)),
    M("saturation_low_rail_strict", "saturation: count_min itself not a rail (C and Python)",
      ((TPL, "raw->{{ field }}[{{ k }}] <= {{ s.count_min }} ||",
        "raw->{{ field }}[{{ k }}] < {{ s.count_min }} ||"),
       (CHAIN, "(raw_counts <= sensor.count_min)", "(raw_counts < sensor.count_min)")),
      tuple(EXPECT)),
    M("saturation_high_rail_off_by_one", "saturation: count_max - 1 flagged (C and Python)",
      ((TPL, ">= {{ s.count_max }}) {", ">= {{ s.count_max }} - 1) {"),
       (CHAIN, "(raw_counts >= sensor.count_max)", "(raw_counts >= sensor.count_max - 1)")),
      tuple(EXPECT)),
    M("nonfinite_coil_ignored", "a non-finite coil current not detected (C and Python)",
      ((TPL, "        finite_probe += aux->coil_A[{{ k }}] - aux->coil_A[{{ k }}];\n", ""),
       (CHAIN, "    for v in inputs.values():\n        nonfinite |=",
        "    for v in [v for k, v in inputs.items() if k != 'coil_A']:\n        nonfinite |=")),
      tuple(EXPECT)),
    M("select_confirmed_needs_two", "selection reason: CONFIRMED only with two agreeing",
      ((TPL, "} else if (n_agree[i] > 0u) {", "} else if (n_agree[i] > 1u) {"),
       (CHAIN, "elif n_agree[i] > 0:", "elif n_agree[i] > 1:")),
      tuple(EXPECT)),
    M("select_two_is_enough", "disagreement with a single other valid sensor",
      ((TPL, "n_cmp[i] >= 2u && 2u", "n_cmp[i] >= 1u && 2u"),
       (CHAIN, "n_cmp[i] >= 2 and 2", "n_cmp[i] >= 1 and 2")),
      tuple(EXPECT)),
    M("fallback_body_first", "fallback order: body before boom",
      ((CHAIN, '0 if e[1].frame == "boom" else 1,', '0 if e[1].frame == "body" else 1,'),),
      tuple(EXPECT)),
    M("lag_zero_dt_moves", "thermal lag: a zero step moves the filter by half",
      ((CHAIN, "return temp_el_C + dt_s / (tau_s + dt_s) * (temp_C - temp_el_C)",
        "return temp_el_C + (dt_s + 1) / (tau_s + dt_s + 2) * (temp_C - temp_el_C)"),),
      tuple(EXPECT)),
    # ---- the chain's maths (one definition: C and Python change together) -------------
    # the kernels (CasADi C and the reference) are folded_sensor_kernel; the constants
    # folded once per table are fold_sensor_coeffs in Python and <unit>_table_prepare in C
    M("offset_added", "offset added instead of subtracted",
      (KERNEL_OFFSET_ADDED,), tuple(FLIGHT)),
    M("coil_sign", "coil coupling added instead of subtracted",
      (KERNEL_COIL_ADDED,), tuple(FLIGHT)),
    M("axis_sign_ignored", "axis signs of the ICD mapping ignored",
      AXIS_SIGN_C + (AXIS_SIGN_PY,), tuple(FLIGHT)),
    M("setreset_not_halved", "SET/RESET difference not halved",
      (SR_HALF_C, SR_HALF_PY), tuple(FLIGHT)),
    M("dT_from_t_min", "polynomials evaluated at T - t_min instead of T - t_ref",
      (T_REF_C, T_REF_PY), tuple(FLIGHT)),
    M("boom_H_transposed", "boom rotation applied transposed",
      (H_FOLD_C, H_FOLD_PY, H_KERNEL), tuple(FLIGHT)),
    M("band_max_not_squared", "plausibility band: field_max not squared",
      (BAND_MAX_C, BAND_MAX_PY), tuple(FLIGHT)),
    # the kernel's own boom rotation (a boom sensor with the SET/RESET rate compensation,
    # which sits between M and H: H is not folded into M)
    M("boom_H_transposed_sr", "boom rotation applied transposed by the kernel (a boom "
      "sensor with SET/RESET rate compensation)", (H_KERNEL,), tuple(FLIGHT)),
    # ---- the fold's bugs in one implementation only: the C prepare or the Python fold ---
    # (the reference and the compiled-in prepared defaults follow the Python fold; the host
    # build's calls, the table manager and the target follow the C prepare)
    M("axis_sign_ignored_C", "axis signs ignored in the C prepare only",
      AXIS_SIGN_C, tuple(FLIGHT)),
    M("axis_sign_ignored_py", "axis signs ignored in the Python fold only",
      (AXIS_SIGN_PY,), tuple(FLIGHT)),
    M("setreset_not_halved_C", "SET/RESET difference not halved in the C prepare only",
      (SR_HALF_C,), tuple(FLIGHT)),
    M("setreset_not_halved_py", "SET/RESET difference not halved in the Python fold only",
      (SR_HALF_PY,), tuple(FLIGHT)),
    M("dT_from_t_min_C", "T - t_min in the C prepare only", (T_REF_C,), tuple(FLIGHT)),
    M("dT_from_t_min_py", "T - t_min in the Python fold only", (T_REF_PY,), tuple(FLIGHT)),
    M("boom_H_transposed_C", "H folded into M transposed in the C prepare only",
      (H_FOLD_C,), tuple(FLIGHT)),
    M("boom_H_transposed_py", "H folded into M transposed in the Python fold only",
      (H_FOLD_PY,), tuple(FLIGHT)),
    M("band_max_not_squared_C", "field_max not squared in the C prepare only",
      (BAND_MAX_C,), tuple(FLIGHT)),
    M("band_max_not_squared_py", "field_max not squared in the Python fold only",
      (BAND_MAX_PY,), tuple(FLIGHT)),
    M("agree_one_sided", "agreement tolerance uses one sensor's scatter only",
      ((CHAIN, "tol = agree[i] + agree[j]", "tol = agree[i] + agree[i] * 0.5"),),
      tuple(EXPECT)),
    # ---- input: the ICD's axis mapping (the fit absorbs it; the truth baseline must not) --
    # a wrong mapping that is a proper rotation (det +1): a fit on the same data absorbs it
    # into M without looking mirrored, so only a baseline independent of the project's
    # preprocessing sees it (a reflection would also meet the fit's mirror check)
    M("preprocess_axes_rotated", "preprocessing: the ICD's frame axes cyclically shifted "
      "(X <- the sensor axis meant for Y, ...)",
      ((PRE, "    idx, sign = spec.axis_map()\n",
        "    idx, sign = spec.axis_map()\n    idx = list(idx)[1:] + list(idx)[:1]\n"),),
      ("host_tests/test_fit_accuracy.py",)),
    M("preprocess_two_signs_flipped", "preprocessing: the ICD's signs of frame X and Y "
      "inverted (a 180 deg turn about Z)",
      ((PRE, "    idx, sign = spec.axis_map()\n",
        "    idx, sign = spec.axis_map()\n    sign = [-sign[0], -sign[1], sign[2]]\n"),),
      ("host_tests/test_fit_accuracy.py",)),
    # a scale error the fit absorbs into M (2 %, inside the part's prior): the fit is at the
    # floor on its own (wrong) nT, the flight chain (its own counts -> nT) is 2 % off; a
    # baseline from the project's preprocessing would be 2 % off too and hide it
    M("preprocess_setreset_scale", "preprocessing: SET/RESET counts -> nT 2 % too large",
      ((PRE, "(raw[j] - raw[3 + j]) / 2.0 * spec.lsb_nT",
        "(raw[j] - raw[3 + j]) / 2.0 * spec.lsb_nT * 1.02"),),
      ("host_tests/test_fit_accuracy.py",)),
    # ---- fits -------------------------------------------------------------------------
    M("fit_offset_biased", "chamber (reference-vector) fit: offsets b0 biased by 0.3 x "
      "the noise floor per axis (~35 x the stated sigma)",
      ((REF, "    return b_poly, M_poly, info",
        "    b_poly = b_poly + 0.3 * np.eye(len(b_poly), 1) * info['residual_sigma_nT']\n"
        "    return b_poly, M_poly, info"),),
      tuple(FIT)),
    M("fit_b_sigma_halved", "chamber fit: stated sigma of b(T) half the truth",
      ((REF, "bsig = sig[:3 * K]", "bsig = 0.5 * sig[:3 * K]"),), tuple(CHI2)),
    M("fit_b_sigma_tripled", "chamber fit: stated sigma of b(T) three times the truth",
      ((REF, "bsig = sig[:3 * K]", "bsig = 3 * sig[:3 * K]"),), tuple(CHI2)),
    M("fit_M_sigma_tripled", "chamber fit: stated sigma of M(T) three times the truth",
      ((REF, "Msig = sig[3 * K:]", "Msig = 3 * sig[3 * K:]"),), tuple(CHI2)),
    M("joint_offset_biased", "joint vector + magnitude fit: offsets b0 biased by 0.3 x the "
      "residual scatter per axis",
      ((JOINT, "bsig = sig[:nb].reshape(degree + 1, 3)",
        "bsig = sig[:nb].reshape(degree + 1, 3)\n"
        "    bp = bp + 0.3 * np.sqrt(s2) * np.eye(degree + 1, 1)"),), tuple(CHI2)),
    M("joint_b_sigma_halved", "joint vector + magnitude fit: stated sigma of b(T) halved",
      ((JOINT, "bsig = sig[:nb]", "bsig = 0.5 * sig[:nb]"),), tuple(CHI2)),
    M("coil_sigma_halved", "stated sigma of K half the truth",
      (("generator/fit/coils.py", "K_sig = np.sqrt(np.outer(np.diag(Ginv), s2)).T",
        "K_sig = 0.5 * np.sqrt(np.outer(np.diag(Ginv), s2)).T"),),
      tuple(CHI2)),
    M("alignment_cov_quartered", "stated covariance of H a quarter of the truth",
      (("generator/fit/alignment.py", "    if s2 == 0.0:\n",
        "    cov = cov / 4\n    if s2 == 0.0:\n"),),
      tuple(CHI2)),
    M("alignment_extra_cov_dropped", "H covariance without the calibrations' uncertainty",
      (("generator/fit/alignment.py", "        cov = cov + 0.5 * (extra + extra.T)\n",
        "        cov = cov + 0.0 * (extra + extra.T)\n"),),
      tuple(CHI2)),
    M("alignment_stat_cov_quartered", "statistical part of the H covariance quartered",
      (("generator/fit/alignment.py", "    cov = cov_stat.copy()\n",
        "    cov = cov_stat.copy() / 4\n"),),
      tuple(CHI2)),
    M("alignment_transposed", "boom alignment H returned transposed",
      (("generator/fit/alignment.py", "    H = wahba_svd(B1, B2, w)\n",
        "    H = wahba_svd(B1, B2, w).T\n"),),
      tuple(CHI2)),
    M("ellipsoid_refine_noop", "ellipsoid refinement turned into a no-op",
      (("generator/fit/ellipsoid.py", "        p, cost, JTJ, lm = lm_solve(model, p0)\n",
        "        _, cost, JTJ, lm = lm_solve(model, p0)\n        p = p0\n"),),
      ("host_tests/test_ellipsoid_partial.py",)),
    # ---- trace rules ------------------------------------------------------------------
    M("trace_block_test_ignored", "trace: the held-out score test over the blocks (p_z; it "
      "replaced the t-test over blocks) ignored",
      ((SCORING, "if not self.p_z * m < alpha:", "if not self.p_z * 0 < alpha:"),),
      tuple(TRACE)),
    M("trace_lr_test_ignored", "trace: the held-out likelihood-ratio test (p_lr) ignored",
      ((SCORING, "if not self.p_lr * m < alpha:", "if not self.p_lr * 0 < alpha:"),),
      tuple(TRACE)),
    M("trace_min_gain_ignored", "trace: the 1 % minimum held-out RMS gain ignored",
      ((SCORING, "        if not gain >= min_gain:",
        "        if not gain >= -float('inf'):"),), tuple(TRACE)),
    # ---- uplink table validator ----------------------------------------------------------
    M("table_crc_unchecked", "flight validator: CRC not checked",
      (("templates/table.c.j2",
        "        return {{ UNIT }}_TABLE_BAD_CRC;\n    }\n    /* content",
        "        (void)0;\n    }\n    /* content"),),
      tuple(TABLES)),
    M("table_layout_unchecked", "flight validator: layout hash not checked",
      (("templates/table.c.j2", "        return {{ UNIT }}_TABLE_WRONG_LAYOUT;\n",
        "        (void)0;\n"),),
      tuple(TABLES)),
    M("table_uninitialised_trusted", "table manager: a manager never initialised counts as "
      "initialised (its zero bytes handed out as coefficients)",
      (("templates/table.c.j2",
        "    return mgr != 0 && mgr->init_mark == {{ UNIT }}_TABLE_INIT_MARK;",
        "    return mgr != 0;"),),
      ("host_tests/test_table_uninitialised.py",)),
]
