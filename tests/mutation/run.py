"""Mutation testing of the core modules with cosmic-ray (MIT), each module against only
the tests that cover it. Not part of CI (minutes to hours on 2 cores).

    pip install "cosmic-ray==8.7.0"
    python tests/mutation/run.py                       # every module below
    python tests/mutation/run.py core/optics.py core/spectra.py
    python tests/mutation/run.py --list                # the module -> tests table
    python tests/mutation/run.py --recheck SESSIONS core/spectra.py  # survivors of a
        # finished session against today's tests (after adding tests; cheap)

Each module is mutated in a scratch copy of the checkout (never in place), one worker,
``pytest -x`` on its test files, 60 s per mutant. Prints a table: mutants, killed,
survived, score; the sessions (``SCRATCH/<module>.sqlite``) stay for
``cr-report --show-diff --surviving-only``. Exit status 0.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if len(sys.argv) > 1 and sys.argv[1] == "--root":  # score another checkout (e.g. "before")
    ROOT = Path(sys.argv[2]).resolve()
    del sys.argv[1:3]

DECONVOLVE = ["tests/test_deconvolve.py", "tests/test_deconvolve_asymmetric.py",
              "tests/test_references.py"]

# module (under pipeline/) -> the test files that cover it
MODULES: dict[str, list[str]] = {
    "core/optics.py": ["tests/test_optics.py", "tests/test_optics_boundaries.py"],
    "core/spectra.py": ["tests/test_psf.py", "tests/test_deconvolve_asymmetric.py",
                        "tests/test_spectra.py"],
    "core/weights.py": ["tests/test_weights.py"],
    "core/stack_kernel.py": ["tests/test_stack_heart.py", "tests/test_engine.py"],
    "core/psf.py": ["tests/test_psf.py", "tests/test_issue11_kills.py"],
    "parallel/accumulate.py": ["tests/test_stack_heart.py", "tests/test_engine.py"],
    "parallel/tiling.py": ["tests/test_tiling.py", "tests/test_deconvolve_asymmetric.py"],
    "core/deconvolve/wiener.py": DECONVOLVE,
    "core/deconvolve/rl.py": DECONVOLVE,
    "core/deconvolve/sparse.py": ["tests/test_sparse_reference.py", *DECONVOLVE],
    "core/align.py": ["tests/test_align.py", "tests/test_issue11_kills.py"],
    "workflow/ledger.py": ["tests/test_workflow.py", "tests/test_issue11_kills.py"],
    "tether/session.py": ["tests/test_tether_ptp.py", "tests/test_tether_emulated.py",
                          "tests/test_issue11_kills.py"],
    "tether/ptp.py": ["tests/test_tether_ptp.py"],
}

# ---- fast selections (helper mutB): ledger, align, ptp, session, rl --------------------------
# Pytest node ids ("file::test") or files, cheapest first (``pytest -x`` stops at the first
# failure); each entry of FULL is the whole covering set, for honest "before" rechecks:
# ``run.py --full --recheck SESSIONS MODULE`` re-runs survivors against FULL[MODULE].
_W, _R, _K = "tests/test_workflow.py", "tests/test_workflow_reliability.py", \
    "tests/test_issue11_kills.py"
_E, _D = "tests/test_tether_emulated.py", "tests/test_tether_defects.py"
_TETHER_FAST = [
    "tests/test_tether_ptp.py", "tests/test_tether_replay.py", "tests/test_tether_layouts.py",
    f"{_K}::test_busy_retries_back_off_exponentially_to_the_cap",
    f"{_K}::test_busy_through_every_retry_gives_up_after_the_last",
    *(f"{_E}::{t}" for t in (
        "test_open_closes_a_stale_session_and_transaction_ids_restart",
        "test_session_vendor_comes_from_the_extension_id_before_the_usb_vendor",
        "test_supports_and_require_name_what_is_missing",
        "test_failures_raise_with_the_response_and_busy_can_be_returned_at_once",
        # helper mut11's session kills
        "test_a_slow_cancel_is_polled_with_doubling_waits_until_idle",
        "test_a_response_to_another_transaction_or_a_second_data_phase_is_a_protocol_error",
        "test_unexpected_data_is_logged_and_expected_data_is_not",
        "test_transaction_ids_of_a_new_session_object_start_at_1",
        "test_open_refused_with_another_code_is_an_error_without_a_close",
        "test_a_response_is_an_immutable_value")),
    f"{_E}::test_downloads_with_zlp_on_both_directions", f"{_E}::test_busy_responses_are_retried",
    f"{_E}::test_timeout_cancels_and_session_stays_usable",
    f"{_E}::test_unsupported_camera_names_missing_operations",
    f"{_E}::test_device_reset_closes_the_session_and_it_can_reopen",
    f"{_E}::test_no_camera_lists_what_was_seen",
    f"{_E}::test_unplug_mid_stack_keeps_downloaded_frames",
    f"{_D}::test_d9_containers_on_packet_boundaries",
    f"{_D}::test_d4_nikon_device_ready_waits_through_a_long_busy_body",
]
_TETHER_FULL = ["tests/test_tether_ptp.py", "tests/test_tether_replay.py",
                "tests/test_tether_layouts.py", "tests/test_tether_bodies.py", _D, _E, _K]
MODULES.update({
    "workflow/ledger.py": [
        *(f"{_W}::{t}" for t in (
            "test_ledger_opens_schema_1_files_and_refuses_other_schemas_and_non_sqlite",
            "test_ledger_round_trips_runs_stacks_and_attempts",
            "test_a_transaction_that_raises_is_rolled_back",
            "test_hash_cache_answers_while_size_mtime_and_inode_match",
            "test_run_lock_file_names_the_holder_and_is_emptied_on_release")),
        f"{_K}::test_a_run_with_failures_is_recorded_failed",
        f"{_K}::test_hash_cache_sees_a_same_size_edit",
        f"{_W}::test_changes_reprocess_affected_stacks_only",
        f"{_W}::test_lock_is_released_by_a_dead_holder",
        f"{_R}::test_an_interrupted_run_does_not_leave_the_ledger_running",
        f"{_R}::test_disk_full_failures_are_retried_on_the_next_run",
        f"{_R}::test_an_output_corrupted_in_place_is_processed_again",
        f"{_W}::test_bad_stacks_fail_alone_with_clear_errors",
    ],
    "core/align.py": [  # no real stacks (4 s): FULL has them
        "tests/test_align_mutation_kills.py",  # helper mut-align: independent references (3 s)
        *(f"tests/test_align.py::{t}" for t in (
            "test_homography_round_trip", "test_compose_applies_rightmost_first",
            "test_scale_of_similarity", "test_invalid_homography",
            "test_warp_identity_returns_input", "test_warp_matches_bilinear_reference",
            "test_warp_integer_shift_and_replicated_border", "test_warp_validates",
            "test_analytic_alignment_scales_about_centre", "test_analytic_alignment_validates",
            "test_alignment_is_a_plain_record", "test_reduction_geometry_matches_cv2_resize",
            "test_similarity_projection_keeps_the_image_centre", "test_estimate_validates",
            "test_implausible_transforms_and_their_boundaries",
            "test_estimate_alignment_validates_its_options")),
        f"{_K}::test_strong_perspective_is_implausible",
        f"{_K}::test_chained_alignment_matches_neighbours",
        f"{_K}::test_unchained_alignment_matches_the_reference",
        *(f"tests/test_align.py::{t}" for t in (
            "test_textureless_uses_given_fallback", "test_noise_frames_do_not_align",
            "test_lazy_frames_are_loaded_once", "test_single_and_identical_frames",
            "test_estimate_colour_frames_and_reduction",
            "test_estimate_direct_and_features_methods",
            "test_analytic_and_estimated_agree", "test_textureless_frame_falls_back",
            "test_estimate_synthetic_stack", "test_features_alone_are_matched_at_the_finest_level",
            "test_parallel_matching_gives_the_serial_result")),
    ],
    "tether/ptp.py": _TETHER_FAST,
    "tether/session.py": _TETHER_FAST,
    "core/deconvolve/rl.py": [
        "tests/test_rl_reference.py",  # helper mut11: against direct sums (~1 s)
        "tests/test_deconvolve.py::test_damped_rl_limits_are_plain_rl_and_no_update",
        "tests/test_deconvolve.py::test_rl_transfer_is_the_iterated_landweber_step",
        "tests/test_deconvolve.py::test_bad_method_and_options_rejected",
        *(f"tests/test_deconvolve.py::{t}[{p}rl]" for t, ps in (
            ("test_delta_kernel_returns_input", ("1-", "5-")),
            ("test_constant_image_stays_constant", ("shape0-", "shape1-")),
            ("test_zero_image_and_zero_pixels", ("",)),
            ("test_channels_are_independent", ("",)),
            ("test_saturated_pixels_excluded", ("",)),
            ("test_zero_noise_and_spectral_zeros_improve", ("",)),
            ("test_huge_kernel", ("",))) for p in ps),
        "tests/test_deconvolve.py::test_rl_negative_pixels_keep_nonnegative_output",
        *(f"tests/test_deconvolve_asymmetric.py::{t}[rl]" for t in (
            "test_methods_undo_a_one_sided_blur_and_the_flip_does_not",
            "test_tiles_with_a_one_sided_kernel_equal_the_whole_frame",
            "test_tiles_honour_the_censored_mask",
            "test_huge_kernel_restoration_is_no_worse_than_its_input")),
        "tests/test_references.py::test_deconvolution_does_not_regress_against_its_reference[rl]",
    ],
})
FULL: dict[str, list[str]] = {
    "workflow/ledger.py": [_W, _R, _K],
    "core/align.py": ["tests/test_align_mutation_kills.py", "tests/test_align.py", _K],
    "tether/ptp.py": _TETHER_FULL,
    "tether/session.py": _TETHER_FULL,
    "core/deconvolve/rl.py": [*DECONVOLVE, "tests/test_rl_reference.py"],
}
# ---- fast selections (helper mutW): weights, accumulate, dispatch, tiling ---------------------
_WT = "tests/test_weights.py"
MODULES["core/weights.py"] = [  # the same tests, cheapest first (the CLI ones last)
    *(f"{_WT}::{t}" for t in (
        "test_weights_validate_their_inputs",
        "test_row_windows_must_fit_inside_the_stack_at_both_ends",
        "test_targets_a_rounding_error_beyond_the_ends_are_accepted",
        "test_whole_millimetre_windows_are_sweeps_too",
        "test_constant_speed_weights_single_frame_and_unsorted_duplicates",
        "test_full_ends_give_equal_weights_for_even_spacing",
        "test_discontinuous_full_range_equals_constant_speed",
        "test_discontinuous_errors", "test_row_weights_outside",
        "test_row_weights_window_is_a_short_sweep",
        "test_discontinuous_concentrates_on_the_ranges",
        "test_full_ends_emulate_a_sweep_half_a_spacing_beyond_the_end_frames",
        "test_row_weights_reproduce_each_rows_position",
        "test_discontinuous_single_range_is_an_interpolated_sweep",
        "test_constant_speed_weights_match_a_sampled_sweep",
        "test_dof_errors", "test_dof_rows_csv_and_in_focus",
        "test_dof_tilted_rows_focus_on_the_plane")),
]
FULL["core/weights.py"] = [_WT]
_SH = "tests/test_stack_heart.py"
MODULES["parallel/accumulate.py"] = [  # test_engine (34 s) only adds the CLI around it
    f"{_SH}::test_weighted_sum_graph_equals_a_numpy_sum",
    f"{_SH}::test_weighted_sum_graph_per_row_weights_and_identity_warps",
    "tests/test_accumulate.py",
]
FULL["parallel/accumulate.py"] = [_SH, "tests/test_engine.py", "tests/test_accumulate.py"]
_DC, _AS, _TL = "tests/test_deconvolve.py", "tests/test_deconvolve_asymmetric.py", \
    "tests/test_tiling.py"
MODULES["core/deconvolve/dispatch.py"] = [  # no sparse quality runs (2-4 s each)
    *(f"{_DC}::{t}" for t in (
        "test_bad_method_and_options_rejected", "test_non_finite_image_rejected",
        "test_bad_kernel_rejected", "test_delta_kernel_returns_input",
        "test_constant_image_stays_constant", "test_zero_image_and_zero_pixels",
        "test_damped_rl_limits_are_plain_rl_and_no_update",
        "test_wiener_is_exact_inverse_without_noise", "test_channels_are_independent[wiener]",
        "test_channels_are_independent[rl]", "test_saturated_pixels_excluded[rl]",
        "test_rl_negative_pixels_keep_nonnegative_output",
        "test_zero_noise_and_spectral_zeros_improve[wiener]",
        "test_zero_noise_and_spectral_zeros_improve[rl]",
        "test_natural_prior_beats_white_prior")),
    *(f"{_AS}::{t}" for t in (
        "test_methods_undo_a_one_sided_blur_and_the_flip_does_not[wiener]",
        "test_methods_undo_a_one_sided_blur_and_the_flip_does_not[rl]",
        "test_tiles_with_a_one_sided_kernel_equal_the_whole_frame[wiener]",
        "test_tiles_with_a_one_sided_kernel_equal_the_whole_frame[rl]",
        "test_wiener_prior_fit_subtracts_the_whole_noise_term")),
    f"{_TL}::test_numpy_input_returns_numpy_and_2d",
    f"{_TL}::test_sparse_is_never_tiled_so_it_equals_the_untiled_result",
    "tests/test_deconvolve_dispatch.py",
]
FULL["core/deconvolve/dispatch.py"] = [*DECONVOLVE, _TL, "tests/test_deconvolve_dispatch.py"]
MODULES["parallel/tiling.py"] = [
    *(f"{_TL}::{t}" for t in (
        "test_bad_tile_size_and_nan_rejected", "test_numpy_input_returns_numpy_and_2d",
        "test_operator_wider_than_frame_uses_one_tile",
        "test_sparse_is_never_tiled_so_it_equals_the_untiled_result")),
    f"{_AS}::test_tiles_with_a_one_sided_kernel_equal_the_whole_frame[wiener]",
    f"{_AS}::test_tiles_with_a_one_sided_kernel_equal_the_whole_frame[rl]",
    "tests/test_tiling_geometry.py",
    f"{_AS}::test_tiles_honour_the_censored_mask[rl]",
    f"{_TL}::test_tiled_equals_untiled_on_uneven_chunks",
]
FULL["parallel/tiling.py"] = [_TL, _AS, "tests/test_tiling_geometry.py"]
# ---- fast selections (helper mutX): psf, wiener/common, workflow run/plan ---------------------
_PS = "tests/test_psf.py"
MODULES["core/psf.py"] = [  # the psf tests of both files, cheapest first (1434 mutants)
    "tests/test_psf_exact.py",
    *(f"{_PS}::{t}" for t in (
        "test_radial_eq6_eq7_match_quadrature_of_eq5",
        "test_encircled_energy_is_integral_of_radial_profile",
        "test_pillbox_raster_is_disk_area[0.3]", "test_pillbox_raster_is_disk_area[1.0]",
        "test_pillbox_raster_is_disk_area[2.5]", "test_gaussian_raster_matches_supersampling",
        "test_lens_psf_in_focus_is_a_delta", "test_sub_pixel_blur_stays_exact",
        "test_printed_eq6_misses_a_factor_two",
        "test_dissimilarity_is_symmetric_and_zero_on_itself",
        "test_zero_blur_kernel_is_delta", "test_zero_speed_reduces_to_lens_psf",
        "test_depth_at_infinity_and_just_beyond_f", "test_kernel_too_large_is_a_clear_error",
        "test_non_positive_lens_parameters_are_named", "test_non_positive_exposure_is_named",
        "test_nan_inputs_are_errors", "test_depth_outside_swept_range",
        "test_mtf_of_delta_is_flat_and_blur_lowers_it",
        "test_three_segment_motion_with_pause_and_reversal", "test_blur_larger_than_500_px",
        "test_depth_invariance_fig5", "test_sweep_starting_or_ending_in_focus",
        "test_analytic_kernel_matches_numeric_eq5")),
    f"{_K}::test_tiny_blur_change_matches_quadrature_and_still_kernel",
    *(f"{_PS}::{t}" for t in (
        "test_kernels_are_valid_and_analytic_equals_numeric",
        "test_pillbox_raster_is_disk_area[7.3]", "test_pillbox_raster_is_disk_area[20.0]",
        "test_analytic_kernel_matches_supersampled_radial_profile")),
]
FULL["core/psf.py"] = [_PS, _K, "tests/test_psf_exact.py"]
_DEC = [  # every test of the Wiener path, cheapest first (measured, 2026-11-26)
    "tests/test_wiener_reference.py",
    "tests/test_deconvolve.py::test_non_finite_image_rejected",
    "tests/test_deconvolve.py::test_bad_kernel_rejected",
    "tests/test_deconvolve.py::test_bad_method_and_options_rejected",
    "tests/test_deconvolve.py::test_noise_sigma_ignores_saturated_blocks",
    "tests/test_deconvolve.py::test_kernel_variance_equals_direct_spectral_variance",
    "tests/test_deconvolve.py::test_kernel_samples_shape_is_checked",
    "tests/test_deconvolve.py::test_rl_transfer_is_the_iterated_landweber_step",
    "tests/test_deconvolve_asymmetric.py::test_eq8_weights_fall_as_one_over_frequency_squared",
    "tests/test_deconvolve_asymmetric.py::test_eq8_dissimilarity_sees_a_flip_of_a_one_sided_kernel",
    "tests/test_wiener_lens_psf.py::test_a_delta_kernel_leaves_a_checkerboard_alone",
    "tests/test_deconvolve_dispatch.py::test_plan_estimates_the_noise_level_when_it_is_not_given",
    "tests/test_deconvolve.py::test_rl_negative_pixels_keep_nonnegative_output",
    "tests/test_deconvolve.py::test_wiener_is_exact_inverse_without_noise",
    "tests/test_deconvolve_asymmetric.py::test_wiener_prior_fit_subtracts_the_whole_noise_term",
    "tests/test_deconvolve_dispatch.py::test_wiener_spectra_are_computed_once_per_grid_and_dtype",
    "tests/test_deconvolve.py::test_damped_rl_limits_are_plain_rl_and_no_update",
    "tests/test_references.py::test_sec41_ipsf_matches_its_reference",
    "tests/test_wiener_lens_psf.py::test_noise_under_a_pixel_scale_texture_is_measured_not_the_texture",
    "tests/test_deconvolve.py::test_noise_sigma_estimate",
    "tests/test_deconvolve.py::test_zero_image_and_zero_pixels",
    "tests/test_deconvolve.py::test_natural_prior_beats_white_prior",
    "tests/test_deconvolve.py::test_constant_image_stays_constant",
    "tests/test_deconvolve_dispatch.py::test_restore_runs_each_channel_with_its_own_noise_level",
    "tests/test_deconvolve.py::test_delta_kernel_returns_input",
    "tests/test_deconvolve_asymmetric.py::test_tiles_with_a_one_sided_kernel_equal_the_whole_frame",
    "tests/test_references.py::test_deconvolution_does_not_regress_against_its_reference",
    "tests/test_deconvolve.py::test_hyper_laplacian_prox_is_the_minimiser",
    "tests/test_deconvolve_dispatch.py::test_named_wrappers_forward_their_options",
    "tests/test_deconvolve_dispatch.py::test_named_wrappers_use_the_methods_own_defaults",
    "tests/test_deconvolve.py::test_channels_are_independent",
    "tests/test_deconvolve_asymmetric.py::test_methods_undo_a_one_sided_blur_and_the_flip_does_not",
    "tests/test_deconvolve.py::test_saturated_pixels_excluded",
    "tests/test_deconvolve.py::test_no_ringing_from_frame_edges",
    "tests/test_deconvolve.py::test_quality_against_ground_truth",
    "tests/test_deconvolve_asymmetric.py::test_huge_kernel_restoration_is_no_worse_than_its_input",
    "tests/test_deconvolve.py::test_huge_kernel",
    "tests/test_deconvolve.py::test_zero_noise_and_spectral_zeros_improve",
    "tests/test_deconvolve_asymmetric.py::test_tiles_honour_the_censored_mask",
    "tests/test_wiener_lens_psf.py::test_pillbox_restoration_is_never_worse_than_its_input",
]
MODULES["core/deconvolve/wiener.py"] = _DEC
FULL["core/deconvolve/wiener.py"] = _DEC
MODULES["core/deconvolve/common.py"] = [*_DEC, _TL]
FULL["core/deconvolve/common.py"] = [*_DEC, _TL]
_GCV = [
    "tests/test_gcv.py",
    "tests/test_wiener_lens_psf.py::test_a_delta_kernel_leaves_a_checkerboard_alone",
]
MODULES["core/deconvolve/gcv.py"] = _GCV
FULL["core/deconvolve/gcv.py"] = [*_GCV, "tests/test_references.py"]
MODULES["core/frame_support.py"] = ["tests/test_frame_support_reference.py",
                                    "tests/test_frame_support.py"]
FULL["core/frame_support.py"] = MODULES["core/frame_support.py"]
# issue 13's guards after the deconvolution (stop 55): cheap unit tests first
MODULES["jobs/ends.py"] = ["tests/test_end_pieces.py", "tests/test_end_detail.py",
                            "tests/test_end_depths.py"]
FULL["jobs/ends.py"] = MODULES["jobs/ends.py"]
MODULES["jobs/frame_detail.py"] = ["tests/test_frame_detail.py"]
FULL["jobs/frame_detail.py"] = MODULES["jobs/frame_detail.py"]
_COLOUR_UNITS = [f"tests/test_end_detail.py::{name}" for name in (
    "test_mean_grey_is_the_channels_mean_for_any_channel_count",
    "test_scale_channels_gives_numpys_broadcast_products_in_place",
    "test_move_grey_reaches_the_target_keeping_the_hue_where_it_can",
    "test_colour_keeps_its_hue", "test_dark_and_undershooting_pixels_are_not_blown_up",
    "test_colour_keeps_its_hue_and_dark_pixels_stay_finite")]
MODULES["core/colour.py"] = ["tests/test_colour.py", "tests/test_io.py", *_COLOUR_UNITS]
FULL["core/colour.py"] = ["tests/test_colour.py", "tests/test_io.py", "tests/test_end_detail.py"]
MODULES["core/defocus.py"] = ["tests/test_defocus_pieces.py", "tests/test_defocus.py",
                              "tests/test_frame_detail.py", "tests/test_end_depths.py"]
FULL["core/defocus.py"] = MODULES["core/defocus.py"]
MODULES["core/exposure.py"] = ["tests/test_exposure.py"]
FULL["core/exposure.py"] = MODULES["core/exposure.py"]
_WF = [  # the workflow tests, cheapest first (measured, 2026-11-26), without the 3 slowest
    "tests/test_workflow_units.py",
    "tests/test_workflow_reliability.py::test_scheduler_address_without_port_is_an_input_error",
    "tests/test_issue11_kills.py::test_a_deleted_sidecar_triggers_a_rerun",
    "tests/test_workflow.py::test_symlink_escape_is_refused",
    "tests/test_workflow.py::test_parse_interval",
    "tests/test_workflow.py::test_shipped_examples_validate",
    "tests/test_workflow.py::test_run_lock_file_names_the_holder_and_is_emptied_on_release",
    "tests/test_workflow_reliability.py::test_a_valueerror_from_numpy_is_not_a_permanent_input_error",
    "tests/test_workflow.py::test_files_grouped_into_stacks_by_regex",
    "tests/test_workflow.py::test_name_collision_is_refused",
    "tests/test_workflow.py::test_hash_cache_answers_while_size_mtime_and_inode_match",
    "tests/test_workflow.py::test_a_transaction_that_raises_is_rolled_back",
    "tests/test_issue11_kills.py::test_hash_cache_sees_a_same_size_edit",
    "tests/test_issue11_kills.py::test_a_run_with_failures_is_recorded_failed",
    "tests/test_workflow_reliability.py::test_an_empty_drop_folder_is_nothing_to_do_yet_for_a_scheduled_workflow",
    "tests/test_workflow_reliability.py::test_every_with_an_empty_drop_folder_is_nothing_to_do_yet",
    "tests/test_workflow_reliability.py::test_a_closed_port_fails_at_once_and_the_ledger_is_not_left_running",
    "tests/test_workflow.py::test_lock_is_released_by_a_dead_holder",
    "tests/test_workflow.py::test_ledger_round_trips_runs_stacks_and_attempts",
    "tests/test_workflow_reliability.py::test_dry_run_prints_its_plan_to_stdout_even_when_quiet",
    "tests/test_workflow_reliability.py::test_file_groups_never_take_the_workflows_own_outputs",
    "tests/test_workflow.py::test_ledger_opens_schema_1_files_and_refuses_other_schemas_and_non_sqlite",
    "tests/test_workflow_reliability.py::test_an_output_folder_inside_the_input_glob_is_not_a_stack",
    "tests/test_workflow_reliability.py::test_an_output_corrupted_in_place_is_processed_again",
    "tests/test_workflow_reliability.py::test_a_banner_from_another_service_is_named",
    "tests/test_workflow_reliability.py::test_an_output_folder_above_the_inputs_excludes_nothing",
    "tests/test_workflow.py::test_output_names_from_inputs_never_escape",
    "tests/test_workflow_reliability.py::test_an_interrupted_run_does_not_leave_the_ledger_running",
    "tests/test_workflow_reliability.py::test_disk_full_failures_are_retried_on_the_next_run",
    "tests/test_workflow.py::test_invalid_workflows_are_refused_before_any_work",
    "tests/test_workflow.py::test_every_loops_with_the_same_guarantees",
    "tests/test_workflow.py::test_changes_reprocess_affected_stacks_only",
    "tests/test_workflow.py::test_bad_stacks_fail_alone_with_clear_errors",
]
_WF_SLOW = [  # 5-13 s each (a killed scheduler, a dashboard port, a killed run): FULL only
    "tests/test_workflow_reliability.py::test_a_dashboard_port_is_reported_as_not_a_scheduler_in_seconds",
    "tests/test_workflow_reliability.py::test_a_scheduler_killed_mid_run_is_one_error_and_the_stacks_are_redone",
    "tests/test_workflow.py::test_killed_run_resumes_without_recomputing",
]
for _m in ("workflow/plan.py", "workflow/run.py"):
    MODULES[_m] = _WF
    FULL[_m] = [*_WF, *_WF_SLOW]
# ---- fast selections (helper mut-sim): the simulator's render, composite, edge ------------
_SR = "tests/test_simulate_reference.py"
_SIM = [  # every test under ~1 s that reaches them, cheapest first (measured, 2026-11-26);
    # FULL adds the slow reference comparisons (rolling shutter, wide angle: 3-45 s each)
    "tests/test_simulate_units.py",  # helper simmut: edge's and composite's units (~2 s)
    "tests/test_simulate_mutation_kills.py",
    f"{_SR}::test_disk_rect_area_exact",
    f"{_SR}::test_reference_and_simulator_agree_where_both_are_exact",
    f"{_SR}::test_sub_aperture_cells_make_a_static_edge_exact",
    f"{_SR}::test_edge_cells_beyond_the_work_budget_keep_over_compositing",
    "tests/test_doctests.py::test_examples_run[pipeline.core.simulate.render]",
    "tests/test_noise_model.py",
    "tests/test_simulate.py",
    f"{_SR}::test_edge_sweep_time_cells_follow_the_tolerance",
]
for _m in ("core/simulate/render.py", "core/simulate/composite.py", "core/simulate/edge.py",
           "core/simulate/planner.py"):
    MODULES[_m] = _SIM
    FULL[_m] = [*_SIM, _SR, "tests/test_applications.py",
                "tests/test_cli_flags.py::test_render_reports_progress_per_step"]
# helper mut-planner: the planner's internals against independent computations (~4 s) first
MODULES["core/simulate/planner.py"] = ["tests/test_planner_units.py", *_SIM]
FULL["core/simulate/planner.py"] = ["tests/test_planner_units.py",
                                    *FULL["core/simulate/planner.py"]]
MODULES["core/deconvolve/gcv.py"] = ["tests/test_gcv_mutation_kills.py", *_GCV]
FULL["core/deconvolve/gcv.py"] = [*MODULES["core/deconvolve/gcv.py"], "tests/test_references.py"]
# ---- end of mutW's selections ----------------------------------------------------------------
# the scratch copy lives in /tmp: point the tests at the real data (else they skip) and
# replay the same hypothesis examples for every mutant
os.environ.setdefault("FLEXDOF_SHARED_DATA", str(ROOT.parent / "shared" / "data"))
os.environ.setdefault("HYPOTHESIS_PROFILE", "ci")
# ---- end of mutB's selections ----------------------------------------------------------------

CONFIG = """[cosmic-ray]
module-path = "{module}"
timeout = {timeout}
excluded-modules = []
test-command = "{python} -m pytest -x -q -p no:cacheprovider {tests}"

[cosmic-ray.distributor]
name = "local"

[cosmic-ray.filters.operators-filter]
# Binary operators are swapped among + - * / ** only: the bitwise, shift, // and %
# swaps on float arrays are ~60% of cosmic-ray's mutants and almost all crash at once
# (a TypeError is not a test of the maths); dropping them makes a module affordable.
exclude-operators = [
    "core/ReplaceBinaryOperator_.*_(FloorDiv|Mod|LShift|RShift|BitOr|BitAnd|BitXor|MatMult)$",
    "core/ReplaceBinaryOperator_(FloorDiv|Mod|LShift|RShift|BitOr|BitAnd|BitXor|MatMult)_.*",
]
"""
TIMEOUT = 60.0
SAMPLE = 1.0
EXCLUDE = 0.0  # --exclude-sample: the mutants of this smaller sample are skipped too


def scratch_copy(dest: Path) -> None:
    for item in ("pipeline", "tests", "pyproject.toml", "lens_profiles", "stacks", "workflows"):
        src = ROOT / item
        if src.is_dir():
            shutil.copytree(src, dest / item, ignore=shutil.ignore_patterns("__pycache__"))
        elif src.exists():
            shutil.copy2(src, dest / item)


def present(tests: list[str], root: Path) -> list[str]:
    """The files and node ids of ``tests`` that exist under ``root`` (an older checkout,
    scored with --root, may lack tests a selection names; pytest would refuse the run)."""
    out = []
    for t in tests:
        path, _, name = t.partition("::")
        if (root / path).exists() and (
            not name or f"def {name.split('[')[0]}(" in (root / path).read_text()
        ):
            out.append(t)
    return out


def score(module: str, work: Path, sessions: Path) -> dict:
    tests = present(MODULES[module], work)
    name = module.replace("/", "_")
    config = sessions / f"{name}.toml"
    session = sessions / f"{name}.sqlite"
    config.write_text(CONFIG.format(module=f"pipeline/{module}", python=sys.executable,
                                    tests=" ".join(tests), timeout=TIMEOUT))
    run = dict(cwd=work, check=True, capture_output=True, text=True)
    subprocess.run(["cosmic-ray", "init", str(config), str(session)], **run)
    subprocess.run(["cr-filter-operators", str(session), str(config)], **run)
    if SAMPLE < 1.0 or EXCLUDE > 0.0:
        sample(session, SAMPLE, EXCLUDE)
    subprocess.run(["cosmic-ray", "exec", str(config), str(session)], **run)
    dump = subprocess.run(["cosmic-ray", "dump", str(session)], **run).stdout
    counts = {"killed": 0, "survived": 0, "incompetent": 0, "pending": 0, "skipped": 0}
    for line in dump.splitlines():
        _, result = json.loads(line)
        if result is not None and result.get("worker_outcome") == "skipped":
            counts["skipped"] += 1
        elif result is None:
            counts["pending"] += 1
        elif result["test_outcome"] == "killed":
            counts["killed"] += 1
        elif result["test_outcome"] == "survived":
            counts["survived"] += 1
        else:
            counts["incompetent"] += 1
    total = counts["killed"] + counts["survived"]
    counts["score"] = 100.0 * counts["killed"] / total if total else float("nan")
    return counts


def in_sample(mutation: dict, fraction: float) -> bool:
    """Whether a mutant is in the ``fraction`` sample: a hash of its module, operator and
    occurrence (not cosmic-ray's random job id), so every session of a module draws the
    same mutants."""
    key = f"{mutation['module_path']}|{mutation['operator_name']}|{mutation['occurrence']}"
    return int(hashlib.sha256(key.encode()).hexdigest()[:8], 16) < fraction * 16**8


def sample(session: Path, fraction: float, exclude: float = 0.0) -> None:
    """Skip the pending mutants outside the ``fraction`` sample (``--sample``) and those
    inside the smaller ``exclude`` sample (``--exclude-sample``: scored before; the
    samples are nested, so this leaves only mutants no earlier session ran)."""
    from cosmic_ray.work_db import use_db
    from cosmic_ray.work_item import WorkerOutcome, WorkResult

    with use_db(str(session)) as db:
        for item in list(db.pending_work_items):
            m = item.mutations[0]
            key = {"module_path": str(m.module_path), "operator_name": m.operator_name,
                   "occurrence": m.occurrence}
            if not in_sample(key, fraction) or (exclude > 0.0 and in_sample(key, exclude)):
                db.set_result(item.job_id, WorkResult(output="not in the --sample",
                                                      worker_outcome=WorkerOutcome.SKIPPED))


def survivors(session: Path, timeouts: bool = False) -> list[dict]:
    """The surviving mutants of a session; with ``timeouts`` also those "killed" by the
    timeout (a machine that pauses niced jobs for a benchmark times out healthy runs)."""
    dump = subprocess.run(["cosmic-ray", "dump", str(session)], check=True,
                          capture_output=True, text=True).stdout
    out = []
    for line in dump.splitlines():
        job, result = json.loads(line)
        if result is not None and (result.get("test_outcome") == "survived" or (
                timeouts and result.get("output") == "timeout")):
            out.append({**job["mutations"][0], "diff": result.get("diff") or ""})
    return out


def _changed_lines(diff: str) -> tuple[list[str], list[str]]:
    """The removed and added lines of a unified diff, stripped (what a mutant changes,
    wherever it sits in the file)."""
    lines = diff.splitlines()
    removed = [x[1:].strip() for x in lines if x.startswith("-") and not x.startswith("---")]
    added = [x[1:].strip() for x in lines if x.startswith("+") and not x.startswith("+++")]
    return removed, added


def _apply(work: Path, m: dict, occurrence: int) -> bytes | None:
    """Apply ``m``'s operator at ``occurrence`` to the scratch copy; the mutated bytes, or
    None when that occurrence does not exist (the file is left unchanged either way)."""
    target = work / m["module_path"]
    source = target.read_bytes()
    try:
        done = subprocess.run(["cosmic-ray", "apply", m["module_path"], m["operator_name"],
                               str(occurrence)], cwd=work, capture_output=True, check=False)
        mutated = target.read_bytes()
    finally:
        target.write_bytes(source)
    return mutated if done.returncode == 0 and mutated != source else None


def _landing(source: bytes, mutated: bytes) -> tuple[int, list[str], list[str]]:
    """Where a mutant changes the file (first changed line, 1-based) and the lines it
    removes and adds, stripped."""
    import difflib

    before, after = source.decode().splitlines(), mutated.decode().splitlines()
    diff = list(difflib.unified_diff(before, after, lineterm="", n=0))
    first = next((i for i, (a, b) in enumerate(zip(before, after)) if a != b), len(before))
    removed, added = _changed_lines("\n".join(diff))
    return first + 1, removed, added


def locate(work: Path, m: dict) -> tuple[bytes, int] | None:
    """The session's mutant applied to today's code, found by its diff, and the line it
    lands on. cosmic-ray numbers a mutant by its occurrence among the operator's sites,
    so code added above it since the session shifts the number and ``apply`` would mutate
    another site (the rechecks of align.py before stop 23 tested some survivors at the
    wrong place). The recorded occurrence is tried first, then its neighbours outwards
    until both ends run out of sites; None when no site makes the session's change (the
    code is gone or was rewritten)."""
    source = (work / m["module_path"]).read_bytes()
    wanted = _changed_lines(m["diff"])
    start, step, up, down = int(m["occurrence"]), 0, True, True
    while up or down:
        for occurrence, side in ((start + step, "up"), (start - step, "down")):
            if (side == "up" and not up) or (side == "down" and not down) or (
                    step == 0 and side == "down"):
                continue
            mutated = _apply(work, m, occurrence) if occurrence >= 0 else None
            if mutated is None:  # past the last site on this side
                if side == "up":
                    up = False
                else:
                    down = False
                continue
            line, removed, added = _landing(source, mutated)
            if not m["diff"] or (removed, added) == wanted:
                return mutated, line
        step += 1
    return None


def recheck(module: str, sessions: Path, full: bool = False, timeouts: bool = False) -> None:
    """Re-run the survivors of ``module``'s session against the current tests (with
    ``timeouts``: also the mutants it timed out, allowed 10 times the timeout)."""
    session = sessions / f"{module.replace('/', '_')}.sqlite"
    table = FULL if full and module in FULL else MODULES
    tests = present(table[module], ROOT)
    cmd = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *tests]
    alive = []
    found = survivors(session, timeouts)
    env = {**os.environ, "PYTHONDONTWRITEBYTECODE": "1"}  # no stale .pyc between mutants
    with tempfile.TemporaryDirectory(prefix="flexdof-mutant-") as tmp:
        work = Path(tmp)
        scratch_copy(work)  # once: each mutant is applied to it and undone after
        for m in found:
            target = work / m["module_path"]
            source = target.read_bytes()
            found_here = locate(work, m)
            if found_here is None:  # the code changed since the session
                print(f"GONE     {m['operator_name']} #{m['occurrence']}", flush=True)
                continue
            mutated, line = found_here
            target.write_bytes(mutated)
            try:
                try:
                    proc = subprocess.run(cmd, cwd=work, capture_output=True, text=True,
                                          check=False, timeout=10 * TIMEOUT, env=env)
                    code = proc.returncode
                except subprocess.TimeoutExpired:
                    code = "timeout"
            finally:
                target.write_bytes(source)
            _report(m, code, alive, line)
    print(f"{module}: {len(found) - len(alive)} of {len(found)} survivors now killed")


def _report(m: dict, code, alive: list, line: int | None = None) -> None:
    """One verdict line: the mutant, and today's line it was applied at (``line``; the
    session's own line when not given)."""
    line = m["start_pos"][0] if line is None else line
    src = (ROOT / m["module_path"]).read_text().splitlines()[line - 1].strip()
    # 1: a test failed, 2: collection failed (the mutant breaks an import);
    # 3-5 are pytest's own errors (a bad node id): never a kill
    verdict = {0: "SURVIVED", 1: "KILLED", 2: "KILLED", "timeout": "TIMEOUT"}.get(code, "ERROR")
    print(f"{verdict:8s} {m['operator_name']} #{m['occurrence']} line {line}: {src[:70]}",
          flush=True)
    if verdict in ("SURVIVED", "ERROR"):  # a hang at 10x the timeout counts as a kill
        alive.append(m)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("modules", nargs="*", help="modules under pipeline/ (default: all)")
    parser.add_argument("--list", action="store_true")
    parser.add_argument("--keep", type=Path, help="folder for the sessions (default: a temp)")
    parser.add_argument("--recheck", type=Path, metavar="SESSIONS",
                        help="re-run the survivors recorded in SESSIONS with today's tests")
    parser.add_argument("--full", action="store_true",
                        help="with --recheck: the module's whole covering files (FULL)")
    parser.add_argument("--timeouts", action="store_true",
                        help="with --recheck: also re-run the mutants that timed out")
    parser.add_argument("--timeout", type=float, default=60.0, help="seconds per mutant")
    parser.add_argument("--sample", type=float, default=1.0, metavar="FRACTION",
                        help="run only this fraction of the mutants (a fixed hash sample)")
    parser.add_argument("--exclude-sample", type=float, default=0.0, metavar="FRACTION",
                        help="skip the mutants of this smaller sample (already scored)")
    args = parser.parse_args(argv)
    global TIMEOUT, SAMPLE, EXCLUDE
    TIMEOUT = args.timeout
    SAMPLE = args.sample
    EXCLUDE = args.exclude_sample
    if args.recheck:
        for module in args.modules:
            recheck(module, args.recheck, args.full, args.timeouts)
        return 0
    if args.list:
        for m, t in MODULES.items():
            print(f"{m:30s} {' '.join(t)}")
        return 0
    modules = args.modules or list(MODULES)
    sessions = args.keep or Path(tempfile.mkdtemp(prefix="flexdof-mutation-"))
    sessions.mkdir(parents=True, exist_ok=True)
    print(f"sessions in {sessions}")
    print(f"| {'module':28s} | mutants | killed | survived | score |")
    print(f"|{'-' * 30}|---------|--------|----------|-------|")
    for module in modules:
        with tempfile.TemporaryDirectory(prefix="flexdof-mutant-") as tmp:
            work = Path(tmp)
            scratch_copy(work)
            c = score(module, work, sessions)
        n = c["killed"] + c["survived"]
        print(f"| {module:28s} | {n:7d} | {c['killed']:6d} | {c['survived']:8d} "
              f"| {c['score']:4.0f}% |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
