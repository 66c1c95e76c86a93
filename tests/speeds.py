"""How long each test file takes, as marks: tests/conftest.py applies them at collection.

``flight`` flies a closed-loop mission, ``process`` spawns processes or subprocesses, ``slow``
takes over about 2 s on a quiet machine. A file maps to the marks of all its tests, or to a
mapping from test names to marks, where ``"*"`` stands for the tests not named. Every test file
is listed (tests/test_speeds.py checks it), so a new file is classified when it is added.
A mapping's ``"*"`` is slow where a file flies, so a new test there stays out of the fast run
until it is named. How the durations were measured: docs/testing.md.
"""

from __future__ import annotations

from collections.abc import Mapping

FLIGHT, PROCESS, SLOW = "flight", "process", "slow"
MARKS = (FLIGHT, PROCESS, SLOW)

Marks = tuple[str, ...]
FAST: Marks = ()
FLIES: Marks = (FLIGHT, SLOW)
SPAWNS: Marks = (PROCESS, SLOW)
BOTH: Marks = (FLIGHT, PROCESS, SLOW)

SPEEDS: dict[str, Marks | Mapping[str, Marks]] = {
    "test_adaptation.py": {
        "*": FLIES,
        "test_a_stalled_host_is_a_blind_spell_not_a_disturbance": FAST,
        "test_cone_in_the_mellinger_layer_keeps_vertical_and_shrinks_horizontal": FAST,
        "test_dob_step_estimates_a_constant_disturbance_without_differentiating": FAST,
        "test_frozen_while_mocap_is_stale_and_reset_on_non_finite_input": FAST,
        "test_mass_step_moves_into_thrust_scale_and_wind_into_offset": FAST,
        "test_mpc_cone_puts_altitude_before_tilt_near_the_clamp": FAST,
        "test_offset_is_held_on_a_saturated_axis_while_the_mass_estimate_learns": FAST,
        "test_rebase_keeps_model_plus_layer_continuous_and_the_model_takes_over": FAST,
        "test_saturated_ticks_never_enter_training_windows": FAST,
        "test_the_ipopt_reference_flies_the_layer_with_the_box": FAST,
    },
    "test_adaptation_engage.py": {
        "*": FLIES,
        "test_a_mass_error_under_the_level_engages_within_seconds": FAST,
        "test_a_small_error_that_persists_engages_through_its_slow_mean_and_holds": FAST,
        "test_a_wind_engages_its_axis_and_a_mass_error_the_vertical": FAST,
        "test_applied_estimate_is_the_model_alone_where_an_axis_does_not_act": FAST,
        "test_engagement_acts_above_the_level_and_lets_go_after_a_quiet_spell": FAST,
        "test_velocity_noise_alone_never_engages_the_layer": FAST,
    },
    "test_adaptation_quiet.py": {
        "*": FLIES,
        "test_a_disturbance_still_reaches_the_offset": FAST,
        "test_a_tracked_step_is_published_without_the_extra_pole": FAST,
        "test_only_the_horizontal_offset_is_shrunk": FAST,
        "test_shrink_silences_small_offsets_and_passes_large_ones": FAST,
        "test_smooth_step_passes_through_at_infinity_and_low_passes_otherwise": FAST,
        "test_velocity_noise_no_longer_reaches_the_offset": (SLOW,),
    },
    "test_adaptation_steps.py": {
        "*": FLIES,
        "test_cusum_accumulates_a_bias_and_forgets_noise": FAST,
        "test_the_accelerometer_tells_the_lag_where_the_frames_cannot": FAST,
        "test_the_lag_bank_picks_the_motor_lag_that_explains_the_climb": FAST,
        "test_the_late_oracle_hears_the_true_mass_after_its_delay": FAST,
    },
    "test_bench_executor.py": {
        "*": BOTH,
        "test_executor_options_are_checked": FAST,
        "test_local_pool_and_this_process_give_the_same_results_in_task_order": SPAWNS,
        "test_local_pool_gives_up_after_max_retries": SPAWNS,
        "test_local_pool_reruns_the_tasks_of_a_dead_worker": SPAWNS,
    },
    "test_bench_hierarchical.py": {
        "*": FLIES,
        "test_markdown_marks_the_lowest_and_counts_wins": FAST,
        "test_quick_hierarchical_bench_runs_the_whole_stack": BOTH,
    },
    "test_bench_online.py": {
        "*": FAST,
        "test_online_beats_nominal_and_offline_on_the_paper_cell": BOTH,
    },
    "test_bench_paper.py": {
        "*": FLIES,
        "test_bench_rejects_bad_arguments": FAST,
    },
    "test_bench_robustness.py": {
        "*": FLIES,
        "test_an_exact_tie_is_the_lowest_for_each_and_bold_for_each": FAST,
        "test_bad_arguments_are_usage_errors": FAST,
        "test_markdown_flags_failures_and_counts_wins": FAST,
        "test_near_ties_count_for_every_controller_within_the_margin": FAST,
        "test_recovery_time_is_when_the_error_settles_back": FAST,
        "test_short_robustness_bench_runs_the_whole_stack": BOTH,
        "test_thrust_to_weight_cells_set_the_thrust_map": FAST,
    },
    "test_bench_rows.py": FAST,
    "test_bench_timing.py": FAST,
    "test_calibrate.py": {
        "*": FAST,
        "test_calibration_against_the_simulator_finds_the_true_mass": FLIES,
    },
    "test_cli.py": {
        "*": BOTH,
        "test_bad_input_is_one_line_and_exit_2": FAST,
        "test_library_log_records_are_held_back_unless_verbose": FAST,
        "test_more_bad_input_is_one_line_and_exit_2": FAST,
    },
    "test_config.py": FAST,
    "test_config_bounds.py": FAST,
    "test_dashboard.py": {
        "*": BOTH,
        "test_costly_frames_are_spaced_out_to_stay_within_the_budget": FAST,
        "test_empty_status_renders_as_not_available": FAST,
        "test_event_panel_shows_on_a_tall_screen_and_gives_way_on_a_short_one": FAST,
        "test_frame_shows_every_panel_and_fits_the_screen": FAST,
        "test_key_reader_does_nothing_off_a_terminal": FAST,
        "test_key_reader_reports_keys_in_cbreak_and_restores_the_terminal": FAST,
        "test_should_show_dashboard": FAST,
        "test_with_dashboard_returns_the_flight_result_and_passes_its_error": FAST,
    },
    "test_estimator.py": FAST,
    "test_estimator_in_flight.py": FLIES,
    "test_estop_mailbox.py": {
        "*": BOTH,
        "test_a_directory_of_another_user_is_refused": FAST,
        "test_a_directory_that_cannot_be_made_is_one_line": FAST,
        "test_a_request_that_cannot_be_read_is_a_stop": FAST,
        "test_a_second_flight_of_a_real_robot_is_refused": FAST,
        "test_a_stale_presence_of_a_dead_process_does_not_refuse": FAST,
        "test_presence_file_names_the_flight_and_its_request": FAST,
        "test_simulated_flights_are_not_named_like_a_robot": FAST,
        "test_the_directory_is_made_private": FAST,
        "test_watcher_errors_are_not_logged_without_bound": FAST,
        "test_watcher_takes_garbage_as_stop_and_says_so": FAST,
    },
    "test_example.py": SPAWNS,
    "test_faults.py": {
        "*": BOTH,
        "test_a_late_mpc_answer_is_replaced_by_the_fallback": FAST,
        "test_every_scenario_file_is_a_valid_config_overlay_and_is_tested": FAST,
        "test_failing_solver_and_nan_model": FAST,
        "test_gust_vehicle_blows_only_during_the_gust": FAST,
        "test_radio_blackout_loses_packets_in_its_window_and_the_link_after_100": FAST,
    },
    "test_fleet.py": {
        "*": FLIES,
        "test_a_pair_too_close_holds_in_place_then_lands": FAST,
        "test_barrier_steps_the_world_only_when_every_loop_waits": FAST,
        "test_downwash_pushes_a_drone_below_down_and_fades_with_distance": FAST,
        "test_fault_policy_decides_what_the_others_do": FAST,
        "test_radio_budget_assigns_links_by_uri_and_refuses_with_the_numbers": FAST,
        "test_references_too_close_are_refused_naming_the_pair_time_and_distance": FAST,
        "test_ring_places_drones_evenly_on_the_circle": FAST,
        "test_separation_watch_ignores_a_pair_that_is_not_flying": FAST,
        "test_stacked_references_never_come_closer_than_the_spacing_and_land_apart": FAST,
    },
    "test_fleet_dashboard.py": {
        "*": FLIES,
        "test_a_closest_approach_under_the_minimum_and_no_drones_tracking_yet": FAST,
        "test_a_poll_that_fails_is_shown_not_raised": FAST,
        "test_each_drone_has_a_row_with_its_errors_tick_times_and_parts": FAST,
        "test_events_show_the_fleets_decisions_and_landings_with_their_cause_not_the_routine_way_up": FAST,
        "test_many_drones_fit_a_small_screen_by_dropping_the_events": FAST,
        "test_the_dashboard_watches_each_drone_draws_beside_the_loop_and_its_keys_land_everyone": FAST,
        "test_the_fleet_shows_its_dashboard_when_a_single_flight_would": FAST,
        "test_the_histogram_quantiles_match_numpys_within_a_bin": FAST,
        "test_the_worst_values_and_drones_not_tracking_are_on_top": FAST,
    },
    "test_fleet_online.py": {
        "*": FLIES,
        "test_a_shared_trainer_answers_each_port_and_a_crash_loses_only_the_queued_rounds": SPAWNS,
    },
    "test_fleet_plot.py": FLIES,
    "test_fleet_ray.py": {
        "*": BOTH,
        "test_a_bad_resource_name_scheme_is_refused_in_one_line": FAST,
        "test_a_drone_whose_radio_no_node_offers_is_refused_naming_it": FAST,
        "test_each_drone_needs_the_resource_named_for_its_radio": FAST,
        "test_the_driver_coordinator_sends_holds_and_timed_landings_to_the_actors": FAST,
        "test_the_timeline_compares_drones_at_the_same_flight_time_however_far_apart_their_actors_run": FAST,
    },
    "test_fleet_robots.py": {
        "*": FLIES,
        "test_a_robots_file_given_to_robots_still_works_with_one_warning": FAST,
        "test_one_connection_serves_every_body_by_name": FAST,
        "test_references_take_off_where_each_robot_stands": FAST,
        "test_robots_names_the_robots_and_robots_file_the_file": FAST,
    },
    "test_fleet_signals.py": {
        "*": FLIES,
        "test_a_second_sigterm_stops_every_drone": BOTH,
        "test_a_stop_signal_in_flight_lands_every_drone": BOTH,
        "test_a_stop_signal_reaches_every_supervisor_and_is_logged_at_the_next_tick": FAST,
    },
    "test_flight_checks.py": FAST,
    "test_flight_sim.py": BOTH,
    "test_flightlog.py": {
        "*": BOTH,
        "test_array_helper": FAST,
        "test_channels_markdown_lists_every_topic": FAST,
        "test_check_message_finds_problems": FAST,
        "test_directory_is_created_and_default_name": FAST,
        "test_every_registered_channel_has_a_sample": FAST,
        "test_idle_log_is_flushed_by_the_background_thread": FAST,
        "test_log_time_is_flight_time_in_ns": FAST,
        "test_not_mcap_is_a_clear_error": FAST,
        "test_numpy_and_non_finite_values": FAST,
        "test_round_trip_of_every_channel": FAST,
        "test_unique_file_names_never_overwrite": FAST,
        "test_write_rejects_bad_input": FAST,
    },
    "test_hardware_backend.py": {
        "*": FLIES,
        "test_a_disabled_robot_is_refused": FAST,
        "test_a_failed_preflight_refuses_take_off_and_hands_the_drone_back": FAST,
        "test_a_missing_radio_closes_the_mocap": FAST,
        "test_force_overrides_a_failed_check_and_says_so": FAST,
        "test_mocap_that_never_answers_fails_before_the_radio_connects": FAST,
    },
    "test_import_contract.py": {
        "*": BOTH,
        "test_the_cycle_finder_finds_loops_and_only_loops": FAST,
    },
    "test_imu.py": {
        "*": FLIES,
        "test_a_bad_imu_noise_is_one_clear_line": FAST,
        "test_a_log_without_imu_fields_replays_with_none": FAST,
        "test_firmware_clock_map_offset_floor_wrap_and_drift": FAST,
        "test_imu_log_off_flies_without_it": FAST,
        "test_lockstep_radio_delivers_every_100_hz_sample_by_its_tick": FAST,
        "test_specific_force_is_gravity_reaction_plus_acceleration_in_the_body_frame": FAST,
        "test_wall_clock_radio_stamps_samples_on_the_flight_clock": FAST,
    },
    "test_knode.py": FAST,
    "test_knode_casadi.py": FAST,
    "test_knode_mpc.py": FLIES,
    "test_latency.py": {
        "*": FLIES,
        "test_constant_command_moves_the_state_by_the_kinematics": FAST,
        "test_estimator_owns_the_predictor_and_reset_clears_it": FAST,
        "test_no_delay_returns_the_estimate_itself": FAST,
        "test_only_the_commands_in_flight_count": FAST,
    },
    "test_learner_with_layer.py": FLIES,
    "test_link_driver.py": FAST,
    "test_log_memory.py": FLIES,
    "test_log_write_failure.py": FLIES,
    "test_logreader.py": {
        "*": FLIES,
        "test_fifo_device_and_directory_are_refused_without_reading": FAST,
    },
    "test_mellinger.py": FAST,
    "test_mocap_sim.py": FAST,
    "test_model_monitor.py": FAST,
    "test_modelfile.py": {
        "*": SPAWNS,
        "test_corrupt_header_bytes": FAST,
        "test_corrupt_length_field": FAST,
        "test_empty_queue_and_no_training_round_trip": FAST,
        "test_integer_tensor_is_rejected": FAST,
        "test_metadata_holds_what_the_design_lists": FAST,
        "test_missing_file": FAST,
        "test_missing_metadata_keys": FAST,
        "test_non_finite_weights_and_normalisation": FAST,
        "test_not_safetensors": FAST,
        "test_other_safetensors_file": FAST,
        "test_pickle_is_never_unpickled": FAST,
        "test_round_trip": FAST,
        "test_save_is_atomic_and_replaces": FAST,
        "test_save_refuses_bad_models_and_leaves_the_old_file": FAST,
        "test_shape_mismatch_with_metadata": FAST,
        "test_tensor_offsets_out_of_range": FAST,
        "test_truncated": FAST,
        "test_wrong_format_version": FAST,
        "test_wrong_layout_activation_and_weights": FAST,
    },
    "test_models_nominal.py": FAST,
    "test_motioncapture_source.py": FAST,
    "test_mpc.py": {
        "*": FAST,
        "test_codegen_compiles_once_and_is_reused": SPAWNS,
    },
    "test_mpc_full.py": {
        "*": FAST,
        "test_hybrid_mpc_equals_the_network_inside_the_graph": (SLOW,),
        "test_input_scaling_and_rotor_polytope": (SLOW,),
    },
    "test_online_flight.py": FLIES,
    "test_online_gate.py": {
        "*": SPAWNS,
        "test_a_window_never_spans_a_model_change": FAST,
        "test_beside_the_fast_layer_a_gain_of_a_few_mm_per_s2_is_noise": FAST,
        "test_beside_the_fast_layer_the_gate_judges_only_what_varies_and_asks_for_a_margin": FAST,
        "test_gate_accepts_a_better_candidate_and_rejects_a_worse_one": FAST,
        "test_gate_rejects_implausible_dynamics_anywhere_in_the_envelope": FAST,
        "test_gate_rejects_non_finite_and_unbounded_models": FAST,
        "test_gate_without_held_out_data_rejects": FAST,
        "test_over_several_steps_a_state_dependent_gain_stands_clear_of_velocity_noise": FAST,
        "test_prediction_is_exact_for_the_true_constant_residual_and_accumulates_over_linked_pairs": FAST,
        "test_recorder_cuts_windows_of_t_col": FAST,
        "test_recorder_does_not_train_on_the_fast_layer_s_transient": FAST,
        "test_recorder_fresh_data_and_long_runs": FAST,
        "test_recorder_skips_ground_and_non_mpc_ticks_and_breaks_the_run": FAST,
        "test_recorder_starts_in_the_air_and_breaks_on_gaps": FAST,
    },
    "test_online_latency.py": FAST,
    "test_online_learner.py": FAST,
    "test_online_signals.py": {
        "*": BOTH,
        "test_the_trainer_process_ignores_stop_signals": SPAWNS,
    },
    "test_online_trainer.py": {
        "*": SPAWNS,
        "test_a_round_learns_the_residual_and_reports_its_metadata": (SLOW,),
        "test_a_round_that_cannot_train_reports_an_error": FAST,
        "test_a_round_with_a_held_out_tail_and_a_replayed_window": FAST,
        "test_renormalise_keeps_the_function": FAST,
    },
    "test_oracle.py": {
        "*": FLIES,
        "test_oracle_thrust_follows_the_true_mass_with_no_offset": FAST,
        "test_oracle_without_a_true_mass_is_refused": FAST,
    },
    "test_paper_controllers.py": {
        "*": FAST,
        "test_latency_learner_gates_swaps_and_pays_its_latency": FLIES,
        "test_lockstep_learner_follows_the_original_schedule": FLIES,
        "test_offline_model_learns_the_first_event_only": FLIES,
        "test_paper_nominal_mpc_reproduces_table_1": FLIES,
    },
    "test_paper_knode.py": FAST,
    "test_paper_protocol.py": FAST,
    "test_plotting.py": {
        "*": FLIES,
        "test_plot_command_rejects_a_file_that_is_not_a_log": FAST,
        "test_the_log_documentation_lists_every_channel": FAST,
    },
    "test_preflight.py": FAST,
    "test_radio.py": FAST,
    "test_recovery.py": FAST,
    "test_replay.py": FLIES,
    "test_replay_mocap.py": FAST,
    "test_residual_np.py": {
        "*": FAST,
        "test_jacobians_match_autograd": (SLOW,),
        "test_module_imports_without_torch": (PROCESS,),
    },
    "test_robots.py": FAST,
    "test_safety_geofence.py": FAST,
    "test_safety_operator.py": FAST,
    "test_safety_supervisor.py": FAST,
    "test_setpoint_reading.py": FAST,
    "test_sim_crazyflie.py": FAST,
    "test_sim_firmware.py": FAST,
    "test_sim_plant.py": {
        "*": FLIES,
        "test_attitude_gain_scales_the_angle_the_firmware_reaches": FAST,
        "test_battery_sag_lowers_the_thrust_over_time": FAST,
        "test_default_plant_keys_are_the_vehicle_config": FAST,
        "test_motor_time_constant_sets_the_plant_lag": FAST,
        "test_plant_keys_are_checked": FAST,
        "test_plant_keys_at_their_defaults_reproduce_the_sim_bit_for_bit": FAST,
        "test_thrust_map_scale_scales_the_force_per_command": FAST,
        "test_thrust_to_weight_helper": FAST,
        "test_yaw_gain_scales_the_yaw_rate": FAST,
    },
    "test_sim_vehicle.py": FAST,
    "test_speeds.py": FAST,
    "test_status.py": FAST,
    "test_step_fit.py": {
        "*": FLIES,
        "test_a_false_alarm_on_mocap_noise_leaves_the_mass_alone": (SLOW,),
        "test_accelerometer_noise_and_offset_raise_no_alarm": (SLOW,),
        "test_the_accelerometer_sees_a_step_a_sample_after_it_and_the_frames_confirm_it": FAST,
        "test_the_accelerometer_vetoes_a_glitch_and_sees_a_step_inside_the_frames_hold": FAST,
        "test_the_layer_knows_the_mass_within_frames_of_a_step_and_does_not_ring": FAST,
        "test_the_step_estimate_from_samples_takes_their_usual_offset_off": FAST,
    },
    "test_stop_signals.py": {
        "*": FLIES,
        "test_a_second_sigterm_stops_the_motors": BOTH,
        "test_a_stop_signal_in_flight_lands_and_hands_back": BOTH,
        "test_process_signals_route_then_restore": FAST,
        "test_sigterm_before_take_off_unwinds_like_ctrl_c": SPAWNS,
    },
    "test_summary.py": FAST,
    "test_thrust_sag.py": {
        "*": FAST,
        "test_every_cell_flies_at_one_height_with_room_for_its_sag": FLIES,
    },
    "test_tick_errors.py": FLIES,
    "test_training.py": {
        "*": FAST,
        "test_regularised_training_recovers_the_physical_residual": (SLOW,),
        "test_training_halves_held_out_error_for_a_heavier_vehicle": (SLOW,),
    },
    "test_trajectory.py": FAST,
    "test_tx_cadence.py": FAST,
}

# Files that share something outside their process run on one pytest-xdist worker, one at a time.
GROUPS: dict[str, str] = {"test_bench_executor.py": "ray", "test_fleet_ray.py": "ray"}


def marks_for(file: str, test: str, table: Mapping[str, Marks | Mapping[str, Marks]] = SPEEDS) -> Marks:
    """The marks of test ``test`` in test file ``file`` (a file not listed has none)."""
    speed = table.get(file, FAST)
    if isinstance(speed, Mapping):
        return speed.get(test, speed.get("*", FAST))
    return speed


def group_for(file: str) -> str:
    """The pytest-xdist group of a test file: its own, unless it shares one."""
    return GROUPS.get(file, file)
