"""verify's diagnosis rules (fab.verify.diagnosis) on hand-made results: what each rule names.

Each result is a plate that is the design with every figure inside its limit
(``_good_result``), changed in the figures a rule reads.
"""

import pytest

from fab.verify import analysis as verify
from fab.verify.analysis import resolve_thresholds
from fab.verify.diagnosis import diagnose


def _good_result(**changes):
    """A verify result of a plate that is the design, with every figure well inside its limit."""
    result = {
        "saturated_dots": 0,
        "window_snr": 1e3,
        "frame_correlation": {"design": 0.99, "rot180": 0.3, "mirror-x": 0.3, "mirror-y": 0.3},
        "zero_order_search": {
            "delta_chi2": {"rot180": -1e3, "mirror-x": -1e3, "mirror-y": -1e3},
            "runner_up_margin": 1e3,
            "transform_psf_correlation": {"rot180": 0.2, "mirror-x": 0.2, "mirror-y": 0.2},
        },
        "correlation": 0.999,
        "correlation_as_measured": 0.999,
        "correlation_with_fitted_etch": 0.999,
        "rmse_with_fitted_etch": 0.01,
        "rmse": 0.01,
        "efficiency": 0.80,
        "efficiency_sigma": 0.01,
        "zero_order": 0.01,
        "zero_order_sigma": 0.001,
        "deep_etch_error_fit": 0.0,
        "deep_etch_error_fit_significance": 0.0,
        "deep_etch_error_joint_fit": None,
        "deep_etch_error_joint_significance": None,
        "overlay_error_fit": None,
        "etch_error_fit": None,
        "overlay_and_etch_fit": None,
        "reflection_set_aside": None,
    }
    result.update(changes)
    result.setdefault("zero_order_excess", result["zero_order"] - 0.01)  # the design's 0.01
    return result


def test_noisy_figures_fail_only_when_they_miss_by_the_significance():
    # "A check on a noisy figure (zero order, efficiency) fails only when it misses
    # its threshold by SIGNIFICANCE (2) sigma."
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    e_min, z_max = t["efficiency_min"], t["zero_order_max"]
    assert diagnose(_good_result(), t) == ["ok"]
    assert diagnose(_good_result(efficiency=e_min - 0.01), t) == ["ok"]  # 1 sigma short
    assert diagnose(_good_result(efficiency=e_min - 0.03), t) == ["low_efficiency"]  # 3 sigma
    assert diagnose(_good_result(zero_order=z_max + 0.001), t) == ["ok"]
    assert diagnose(_good_result(zero_order=z_max + 0.003), t) == ["zero_order_excess"]
    # 1.5 sigma past the limit still passes: the 1-sigma cases above sit on a rounding edge
    assert diagnose(_good_result(efficiency=e_min - 0.015, zero_order=z_max + 0.0015), t) == ["ok"]


def test_default_thresholds_are_relative_to_the_design_and_fail_a_psf_below_095():
    # catches a default correlation_min under the documented 0.95 and absolute limits
    t = resolve_thresholds(None, design_efficiency=0.6, design_zero_order=0.05)
    assert t["efficiency_min"] == pytest.approx(0.85 * 0.6)
    assert t["zero_order_max"] == pytest.approx(0.05 + 0.01)
    assert diagnose(_good_result(correlation=0.93), t) == ["psf_mismatch"]


def test_a_deep_etch_fit_under_three_sigma_does_not_fail_the_plate():
    # catches a chi-square bar of 4 (2 sigma): a one-parameter fit to noise alone drops
    # the chi-square by over 4 in 4.6 % of captures, by over 9 (3 sigma) in 0.27 %
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    fit = {"deep_etch_error_fit": -0.15}
    assert diagnose(_good_result(**fit, deep_etch_error_fit_significance=6.0), t) == ["ok"]
    # and it must lie beyond the tolerance (0.10) by 2 sigma: a gain of 12 puts -0.15 at
    # 0.043 sigma, 1.2 sigma beyond; a gain of 40 at 0.024, 2.1 sigma beyond
    beyond_by_one = _good_result(**fit, deep_etch_error_fit_significance=12.0)
    assert diagnose(beyond_by_one, t) == ["ok"]
    failing = _good_result(**fit, deep_etch_error_fit_significance=40.0)
    assert diagnose(failing, t) == ["deep_etch_error"]


def test_a_deep_etch_fit_past_its_tolerance_is_named_only_when_the_joint_fit_agrees():
    # A mid etch 45 % off moved the deepest etch's own fit past its tolerance on a passing
    # PSF: the plate was named deep_etch_error, the wrong mask. (Own fit 0.13 +- 0.0065:
    # beyond the 0.10 by 2 sigma.)
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    own = dict(deep_etch_error_fit=0.13, deep_etch_error_fit_significance=400.0)
    for joint, gain, named in ((0.0, 0.5, False), (0.104, 40.0, True), (0.09, 40.0, False)):
        result = _good_result(
            **own, deep_etch_error_joint_fit=joint, deep_etch_error_joint_significance=gain
        )
        assert diagnose(result, t) == (["deep_etch_error"] if named else ["ok"])


def test_a_deep_etch_within_its_tolerance_is_named_when_it_explains_a_failing_psf():
    # 9.8 % off failed a random design's PSF (correlation 0.61) as a bare psf_mismatch
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    within = dict(deep_etch_error_fit=-0.098, deep_etch_error_fit_significance=1e4)
    failing = dict(within, correlation=0.6, rmse=0.1)
    assert diagnose(_good_result(**failing), t) == ["deep_etch_error", "psf_mismatch"]
    assert diagnose(_good_result(**within), t) == ["ok"]  # a PSF that passes: within tolerance
    unexplained = dict(failing, correlation_with_fitted_etch=0.9)
    assert diagnose(_good_result(**unexplained), t) == ["other_design"]
    assert diagnose(_good_result(**failing, rmse_with_fitted_etch=0.1), t) == ["psf_mismatch"]
    weak = dict(failing, deep_etch_error_fit_significance=8.0)
    assert diagnose(_good_result(**weak), t) == ["psf_mismatch"]


def test_a_deep_etch_within_its_tolerance_is_named_when_it_explains_a_brightened_zero_order():
    # The PSF within, the zero order 4 % over the design's: zero_order_excess alone told
    # the lab nothing of which etch to remeasure.
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    bright = dict(zero_order=0.05, deep_etch_error_fit=0.06, deep_etch_error_fit_significance=600.0)
    agreed = dict(deep_etch_error_joint_fit=0.058, deep_etch_error_joint_significance=57.0)
    assert diagnose(_good_result(**bright, **agreed), t) == ["zero_order_excess", "deep_etch_error"]
    # the others' fit puts the deepest at 0: the brightening is another etch's
    noise = dict(deep_etch_error_joint_fit=-0.001, deep_etch_error_joint_significance=0.1)
    assert diagnose(_good_result(**bright, **noise), t) == ["zero_order_excess"]
    unexplained = dict(bright, **agreed, correlation_with_fitted_etch=0.9)
    assert diagnose(_good_result(**unexplained), t) == ["zero_order_excess"]
    # over an absolute zero_order_max but no brighter than the design's own: no plate fault
    absolute = dict(correlation_min=0.99, rmse_max=0.02, efficiency_min=0.5, zero_order_max=0.005)
    strict = resolve_thresholds(absolute, 0.80, 0.05)
    as_designed = dict(bright, **agreed, zero_order_excess=0.0)
    assert diagnose(_good_result(**as_designed), strict) == ["zero_order_excess"]


def _overlay(**changes):
    fit = {"mask": "M2_mid", "shift_px": [1.5, 0.0], "significance": 1e4, "correlation": 0.999,
           "rmse": 0.005, "frame_correlation": 0.99}  # fmt: skip
    return {**fit, **changes}


def test_an_overlay_fit_names_a_failing_plate_only_when_it_explains_it_decisively():
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    failing = dict(correlation=0.6, correlation_with_fitted_etch=0.6, rmse=0.1)
    assert diagnose(_good_result(**failing), t) == ["other_design"]
    explained = _good_result(**failing, overlay_error_fit=_overlay())
    assert diagnose(explained, t) == ["overlay_error", "psf_mismatch"]
    for weak in (
        _overlay(significance=8.0),  # under 3 sigma
        _overlay(correlation=0.94),  # not within the thresholds either
    ):
        assert diagnose(_good_result(**failing, overlay_error_fit=weak), t) == ["other_design"]
    # beyond the reach an overlay is named in: not named, but still this design's plate
    for beyond in (_overlay(shift_px=[2.0, 0.3]), _overlay(shift_px=[0.2, -2.4])):
        assert diagnose(_good_result(**failing, overlay_error_fit=beyond), t) == ["psf_mismatch"]
    # within the thresholds but no better than a deep-etch error: that is named instead
    etch = dict(failing, correlation_with_fitted_etch=0.999, deep_etch_error_fit=0.2,
                deep_etch_error_fit_significance=1e4)  # fmt: skip
    assert diagnose(_good_result(**etch, overlay_error_fit=_overlay()), t) == [
        "deep_etch_error", "psf_mismatch"
    ]  # fmt: skip
    better = _good_result(**etch, overlay_error_fit=_overlay(correlation=0.9995))
    assert diagnose(better, t) == ["overlay_error", "psf_mismatch"]
    # a dense design: an overlay changes every order, so the design's frame fails but
    # the fitted plate's frame must hold too
    dense = dict(failing, frame_correlation=dict(_good_result()["frame_correlation"], design=0.4))
    assert diagnose(_good_result(**dense), t) == ["other_design"]
    assert diagnose(_good_result(**dense, overlay_error_fit=_overlay()), t) == [
        "overlay_error", "psf_mismatch"
    ]  # fmt: skip
    unlike = _overlay(frame_correlation=0.5)
    assert diagnose(_good_result(**dense, overlay_error_fit=unlike), t) == ["other_design"]
    # a fitted rmse beyond the threshold: this design (correlation 0.999), but the
    # overlay is no explanation within the thresholds
    assert diagnose(_good_result(**failing, overlay_error_fit=_overlay(rmse=0.09)), t) == [
        "psf_mismatch"
    ]  # fmt: skip


def _etch(errors=(0.0, 0.25, 0.0), mask_significance=(0.5, 1e4, 0.3), **changes):
    fit = {"masks": ["M1_deep", "M2_mid", "M3_shallow"], "errors": list(errors),
           "mask_significance": list(mask_significance), "at_search_edge": False,
           "significance": 1e4, "correlation": 0.999, "rmse": 0.005,
           "frame_correlation": 0.99}  # fmt: skip
    return {**fit, **changes}


def test_an_etch_fit_names_a_failing_plate_only_when_a_shallower_etch_explains_it_best():
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    failing = dict(correlation=0.6, correlation_with_fitted_etch=0.6, rmse=0.1)
    explained = _good_result(**failing, etch_error_fit=_etch())
    assert diagnose(explained, t) == ["etch_depth_error", "psf_mismatch"]
    for weak in (
        _etch(significance=8.0),  # under 3 sigma in all
        _etch(mask_significance=(0.5, 8.0, 0.3)),  # M2's error is not needed
        _etch(errors=(0.3, 0.0, 0.0), mask_significance=(1e4, 0.1, 0.1)),  # the deepest alone
        _etch(at_search_edge=True),  # an error may lie beyond the search
        _etch(correlation=0.94),  # not within the thresholds
    ):
        assert diagnose(_good_result(**failing, etch_error_fit=weak), t) == ["other_design"]
    # the deepest etch off beside a shallower one: named, by the joint fit's error
    both = dict(errors=(-0.15, 0.25, 0.0), mask_significance=(1e4, 1e4, 0.3))
    assert diagnose(_good_result(**failing, etch_error_fit=_etch(**both)), t) == [
        "etch_depth_error", "deep_etch_error", "psf_mismatch"
    ]  # fmt: skip
    within = dict(errors=(-0.05, 0.25, 0.0), mask_significance=(1e4, 1e4, 0.3))  # under 10 %
    assert diagnose(_good_result(**failing, etch_error_fit=_etch(**within)), t)[0:2] == [
        "etch_depth_error", "psf_mismatch"
    ]  # fmt: skip
    # of an overlay and an etch fit that both explain the window, the closer is named
    for etch_corr, named in ((0.9995, "etch_depth_error"), (0.9985, "overlay_error")):
        both = _good_result(
            **failing, overlay_error_fit=_overlay(), etch_error_fit=_etch(correlation=etch_corr)
        )
        assert diagnose(both, t) == [named, "psf_mismatch"]
    # no better than the deep-etch fit: that is named instead
    deep = dict(failing, correlation_with_fitted_etch=0.999, deep_etch_error_fit=0.2,
                deep_etch_error_fit_significance=1e4)  # fmt: skip
    assert diagnose(_good_result(**deep, etch_error_fit=_etch()), t) == [
        "deep_etch_error", "psf_mismatch"
    ]  # fmt: skip
    # a dense design: the fitted plate's frame must hold where the design's fails
    dense = dict(failing, frame_correlation=dict(_good_result()["frame_correlation"], design=0.4))
    assert diagnose(_good_result(**dense, etch_error_fit=_etch()), t)[0] == "etch_depth_error"
    unlike = _etch(frame_correlation=0.5)
    assert diagnose(_good_result(**dense, etch_error_fit=unlike), t) == ["other_design"]


def _both(**changes):
    fit = {"mask": "M1_deep", "shift_px": [1.5, 0.0], "shift_significance": 1e5,
           "masks": ["M1_deep", "M2_mid", "M3_shallow"], "errors": [0.0, 0.3, 0.0],
           "mask_significance": [1.0, 1e4, 0.5], "at_search_edge": False, "significance": 1e4,
           "correlation": 0.999, "rmse": 0.005, "frame_correlation": 0.99}  # fmt: skip
    return {**fit, **changes}


def test_an_overlay_and_etch_fit_names_both_faults_only_when_both_are_needed():
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    # the two fits alone explain the window in part only (correlation 0.9)
    alone = dict(overlay_error_fit=_overlay(correlation=0.9), etch_error_fit=_etch(correlation=0.9))
    failing = dict(correlation=0.6, correlation_with_fitted_etch=0.6, rmse=0.1, **alone)
    assert diagnose(_good_result(**failing), t) == ["other_design"]
    named = _good_result(**failing, overlay_and_etch_fit=_both())
    assert diagnose(named, t) == ["overlay_error", "etch_depth_error", "psf_mismatch"]
    deep = _both(errors=[-0.2, 0.0, 0.0], mask_significance=[1e4, 0.3, 0.5])
    assert diagnose(_good_result(**failing, overlay_and_etch_fit=deep), t) == [
        "overlay_error", "deep_etch_error", "psf_mismatch"
    ]  # fmt: skip
    for weak in (
        _both(significance=8.0),  # no better than one fault alone
        _both(shift_significance=8.0),  # the shift is not needed
        _both(mask_significance=[1.0, 8.0, 0.5]),  # nor any etch error
        _both(at_search_edge=True),
        _both(correlation=0.94),
    ):
        assert diagnose(_good_result(**failing, overlay_and_etch_fit=weak), t) == [
            "other_design"
        ]  # fmt: skip


def test_a_reflection_names_the_plate_only_when_it_explains_the_window():
    # A plate of another design won as the conjugate of a nearly point-symmetric design
    # (frame 0.83, chi-square 35 better) and matched that conjugate's PSF at 0.85 only.
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    won = dict(
        frame_correlation={"design": 0.82, "rot180": 0.83, "mirror-x": 0.3, "mirror-y": 0.3},
        zero_order_search=dict(
            _good_result()["zero_order_search"],
            delta_chi2={"rot180": 35.0, "mirror-x": -1e3, "mirror-y": -1e3},
        ),
        correlation=0.5,
    )
    assert diagnose(_good_result(**won), t) == ["conjugate_plate"]
    assert diagnose(_good_result(**won, correlation_as_measured=0.85), t) == ["other_design"]


def test_a_runner_up_offset_within_25_of_the_best_chi_square_is_ambiguous():
    # the zero order one place further fits nearly as well: where is the PSF's centre?
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)

    def with_margin(margin):
        search = dict(_good_result()["zero_order_search"], runner_up_margin=margin)
        return diagnose(_good_result(zero_order_search=search), t)

    assert with_margin(24.0) == ["zero_order_ambiguous"]
    assert with_margin(26.0) == ["ok"]


def test_a_window_under_30_times_its_noise_is_low_signal():
    # catches a lower signal-to-noise bar than the documented MIN_WINDOW_SNR of 30
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    assert diagnose(_good_result(window_snr=20.0), t) == ["low_signal"]


@pytest.mark.parametrize(
    "fault, change", [("saturated", {"saturated_dots": 3}), ("low_signal", {"window_snr": 5.0})]
)
def test_a_clipped_or_noisy_capture_is_not_called_another_design(fault, change):
    # catches "other_design" added after these: the window of a clipped or noisy capture
    # correlates poorly with any design, and the lab would remake a good plate
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    poor = _good_result(correlation=0.6, correlation_with_fitted_etch=0.6, **change)
    assert diagnose(poor, t) == [fault]


def test_a_reflection_near_the_design_is_no_ambiguity_where_a_fitted_fault_explains_more():
    # M2 45 % off left a mirror within 9 of the bare design: zero_order_ambiguous, though
    # the design with the fitted etch explained the window at 0.9999, the frame at 1.000
    strict = dict(correlation_min=0.99, rmse_max=0.02, efficiency_min=0.5, zero_order_max=0.05)
    t = resolve_thresholds(strict, 0.80, 0.01)
    search = _good_result()["zero_order_search"]
    near = {**search, "delta_chi2": {**search["delta_chi2"], "mirror-y": -9.0}}
    frames = {"design": 0.9, "rot180": 0.3, "mirror-x": 0.3, "mirror-y": 0.92}
    failing = dict(correlation=0.96, correlation_with_fitted_etch=0.96, rmse=0.03,
                   zero_order_search=near, frame_correlation=frames)  # fmt: skip
    assert diagnose(_good_result(**failing), t) == ["zero_order_ambiguous"]
    explained = _good_result(**failing, etch_error_fit=_etch(frame_correlation=1.0))
    assert diagnose(explained, t) == ["etch_depth_error", "psf_mismatch"]
    for weak in (
        _etch(frame_correlation=0.91),  # the mirror fits the frame better
        _etch(frame_correlation=1.0, significance=8.0),  # not decisive
        _etch(frame_correlation=1.0, correlation=0.98),  # not within the thresholds
        _etch(frame_correlation=1.0, rmse=0.05),
        _etch(frame_correlation=1.0, at_search_edge=True),  # may lie beyond the search
    ):
        assert diagnose(_good_result(**failing, etch_error_fit=weak), t) == ["zero_order_ambiguous"]
    # an overlay pinned at the edge of its reach explains nothing either
    pinned = _overlay(shift_px=[2.0, 0.5], frame_correlation=1.0)
    assert diagnose(_good_result(**failing, overlay_error_fit=pinned), t) == [
        "zero_order_ambiguous"
    ]


def test_a_reflection_set_aside_is_not_named():
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    search = _good_result()["zero_order_search"]
    wins = {**search, "delta_chi2": {**search["delta_chi2"], "mirror-y": 60.0}}
    frames = {"design": 0.9, "rot180": 0.3, "mirror-x": 0.3, "mirror-y": 0.92}
    mirrored = dict(zero_order_search=wins, frame_correlation=frames)
    assert diagnose(_good_result(**mirrored), t) == ["mirrored"]
    assert diagnose(_good_result(**mirrored, reflection_set_aside="mirror-y"), t) == ["ok"]


def test_a_winning_reflection_is_set_aside_only_for_a_fault_that_fits_the_frame_better(
    monkeypatch,
):
    # A deep etch 45 % off had a mirror fit the default design's frame better than the
    # bare design; the design with the fitted etch fitted it better still.

    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    frames = {"design": 0.9, "rot180": 0.3, "mirror-x": 0.3, "mirror-y": 0.95}
    reflected = _good_result(frame_correlation=frames, measured_as="mirror-y")
    for fault_frame, set_aside in ((0.99, True), (0.94, False)):
        as_design = _good_result(
            frame_correlation=frames,
            measured_as="design",
            correlation=0.6,
            rmse=0.1,
            etch_error_fit=_etch(errors=(0.45, 0.0, 0.0), frame_correlation=fault_frame),
        )
        calls = []

        def fake(plate, *args, as_design=as_design, calls=calls):
            calls.append(plate)
            return (dict(reflected) if plate is None else dict(as_design)), None

        monkeypatch.setattr(verify, "_analyse_as", fake)
        result, _ = verify.analyse(None, None, 8, 11, "as-designed", t)
        assert calls == [None, "design"]
        assert result["measured_as"] == ("design" if set_aside else "mirror-y")
        assert result["reflection_set_aside"] == ("mirror-y" if set_aside else None)


def test_a_fitted_plate_lighting_its_zero_order_alone_leaves_the_frame_unjudged():
    # a near-delta design's mid etch 30 % off: the orders beside the zero order fell to
    # the noise, and correlated at 0.21 with the design's (other_design)
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    frames = {"design": 0.21, "rot180": 0.21, "mirror-x": 0.21, "mirror-y": 0.21}
    plate = dict(frame_correlation=frames, correlation=0.9995, zero_order=0.05)
    flat = _etch(frame_correlation=float("nan"), correlation=1.0)
    assert diagnose(_good_result(**plate, etch_error_fit=flat), t) == [
        "zero_order_excess",
        "etch_depth_error",
    ]
    assert diagnose(_good_result(**plate), t) == ["other_design"]  # no such fit
    weak = _etch(frame_correlation=float("nan"), correlation=1.0, significance=8.0)
    assert diagnose(_good_result(**plate, etch_error_fit=weak), t) == ["other_design"]


def test_the_deepest_etch_is_not_named_where_a_fit_at_the_edge_of_its_reach_explains_more():
    # An 11 um overlay of M1 (2.25 mask pixels, past the fit's 2) on a sparse design was
    # named deep_etch_error: the overlay fit, pinned at 2.0 px, matched the window at
    # 0.9998, the deepest etch's own fit at 0.9994.
    t = resolve_thresholds(None, design_efficiency=0.80, design_zero_order=0.01)
    deep = dict(
        deep_etch_error_fit=0.12,
        deep_etch_error_fit_significance=500.0,
        deep_etch_error_joint_fit=0.12,
        deep_etch_error_joint_significance=400.0,
        correlation_with_fitted_etch=0.9994,
    )
    assert diagnose(_good_result(**deep), t) == ["deep_etch_error"]
    pinned = _overlay(shift_px=[2.0, -0.24], correlation=0.9998)
    assert diagnose(_good_result(**deep, overlay_error_fit=pinned), t) == ["ok"]
    worse = _overlay(shift_px=[2.0, -0.24], correlation=0.999)
    assert diagnose(_good_result(**deep, overlay_error_fit=worse), t) == ["deep_etch_error"]
    inside = _overlay(shift_px=[1.9, -0.24], correlation=0.9998, significance=8.0)
    assert diagnose(_good_result(**deep, overlay_error_fit=inside), t) == ["deep_etch_error"]
