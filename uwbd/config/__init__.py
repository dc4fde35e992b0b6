"""uwbd's TOML configuration, validated into typed objects.

:func:`parse` checks the whole file and reports every problem at once: one
:class:`ConfigError` whose ``problems`` are lines ``"{file}: {key}: {what}"``, the key spelt
as in the TOML (``sources[1].port``, ``fusion.range_sigma_m``, ``anchors.3``,
``zenoh.listen[0]``), type errors with the type expected (``fusion.zupt: expected true or
false, got "yes" (a string)``). Unknown keys are errors too, since a misspelt option that is
silently ignored is worse than none. What is only suspicious (a non-standard baud rate, a
noise density 100x off its default, exactly 3 anchors) lands in ``Config.warnings``.
Sections::

    [robot]              name (this machine's host name): in log names, metadata and the Zenoh
                         prefix; nav_frame_id ("enu"), body_frame_id ("base_link"): the frame
                         names in poses, transforms and ROS 2 bags
    [[sources]]          name, driver, port, baud
    [anchors]            "<id>" = [x, y, z]            (m, navigation frame ENU), or
                         "<id>" = { position_m = [x, y, z], orientation_xyzw = [qx, qy,
                         qz, qw] } (the antenna's axes in the navigation frame, for the
                         range model's anchors' term; ``uwbd import inrol`` writes them)
    [imu]                mounting = 3x3 rows (sensor -> body FLU), lever_arm_m = [x, y, z],
                         noise densities from the IMU's datasheet (defaults: a consumer MEMS
                         part with margin for vibration): acc_noise_mps2_rthz (0.01),
                         gyro_noise_rps_rthz (0.001), acc_bias_walk_mps3_rthz (0.001),
                         gyro_bias_walk_rps2_rthz (0.0001); the full scale the sensor is set
                         to: acc_full_scale_mps2 (16 g), gyro_full_scale_rps (2000 °/s);
                         intrinsics per sensor axis (``uwbd calibrate-imu`` writes them),
                         a_true = (a_meas − acc_offset_mps2) / acc_scale: acc_scale ([1, 1,
                         1], each 0.8..1.2), acc_offset_mps2 ([0, 0, 0], each within ±2),
                         gyro_offset_rps ([0, 0, 0], each within ±0.5), gyro_deadband_rps
                         (0: off; at most 0.1), and gravity_mps2 (9.80665; 9.7..9.9, a
                         warning outside 9.77..9.84)
    [fusion]             mode, range_sigma_m, range_bias_states, range_bias_sigma_m (0.1:
                         each anchor's antenna delay), tag_delay_sigma_m (0.2: the tag's),
                         zupt, nhc, known_height_m, gate_probability, min_anchors, max_range_m,
                         robust (true: NLOS de-weighted), nlos_onset_m (unset: 2.5
                         range_sigma_m; ``uwbd calibrate-ranges`` writes it: a range this much
                         longer than predicted is de-weighted as likely NLOS),
                         multipath_sigma_m (0.07; 0: off) and
                         multipath_tau_s (1): time-correlated range error per anchor
                         (``uwbd calibrate-ranges`` writes both),
                         tag_side ("auto", "below", "above" a plane of anchors),
                         height_range_m ([lo, hi]: where the tag can be, a mirror hint)
    [range_model]        (``uwbd calibrate-ranges`` writes it; all off by default)
                         tag_degree (0..3; 0: no direction term), tag_coefficients_m (the
                         tag antenna's direction-dependent delay: real spherical harmonics
                         of degrees 1..tag_degree, m = -l..l each, tag axes), tag_mounting
                         (3x3 rows, tag axes -> body; identity), anchor_delays_m ({ "<id>" =
                         delay }: taken off each anchor's ranges), log_distance_m (k ≥ 0
                         of the delay k ln(d / 1 m) that grows with distance; 0),
                         anchor_degree (0..3; 0: none) and anchor_coefficients_m (the
                         anchors' own direction term, the ray in each one's axes, common to
                         the units; applied to anchors given with an orientation),
                         calibrated_from (a note)
    [pipeline]           aligner_wait_ms (0), pose_rate_hz (50), status_period_s (1),
                         stall_after_s (1: a port silent this long is "stalled")
    [log]                directory ("logs"), rotate_mb (256), rotate_minutes (60)
    [zenoh]              enabled (true), mode ("peer"), connect [], listen [], prefix
                         ("uwbd/<robot name>"), multicast_scouting (true), config (a Zenoh
                         config file, JSON5: TLS, authentication, access control; the keys
                         above that the table gives are set over it, the others are the
                         file's, else these defaults, never Zenoh's own)

Beyond types and ranges (the tables in :mod:`uwbd.config.schema`), the file must make sense
as a whole (:mod:`uwbd.config.checks`): with sources, one of them is UWB; a driver that
reports ranges only (``nlink``) needs 3 anchors or more with ids it can report; anchors lie
apart, within 10 km; Zenoh endpoints parse (and Zenoh itself accepts them); ``imu.mounting``
is a rotation, and each axis of the IMU's intrinsics plausible. A config without sources is
one for replaying or importing logs.
:func:`apply_overrides` sets keys from the command line (``fusion.zupt=false``) and returns
the TOML actually used; :func:`to_toml` writes one for given settings.

Modules: :mod:`~uwbd.config.model` (what a parsed config is), :mod:`~uwbd.config.schema`
(what each key may hold), :mod:`~uwbd.config.reading` (reading a file),
:mod:`~uwbd.config.checks` (the file as a whole), :mod:`~uwbd.config.overrides` (``--set``,
writing TOML), :mod:`~uwbd.config.spelling` (how messages spell keys and values).
"""

from uwbd.config.model import (
    IMU_INTRINSIC_KEYS,
    IMU_LIMIT_KEYS,
    IMU_NOISE_KEYS,
    Config,
    ConfigError,
    SourceConfig,
    Vec3,
    default_robot_name,
)
from uwbd.config.overrides import apply_overrides, to_toml
from uwbd.config.reading import MAX_CONFIG_BYTES, load, parse
from uwbd.config.schema import (
    G_MPS2,
    IMU_DRIVERS,
    MIN_ANCHOR_SPACING_M,
    NOISE_PLAUSIBLE_FACTOR,
    ROTATION_TOLERANCE,
    STANDARD_BAUDS,
    UWB_DRIVERS,
    ZENOH_PROTOCOLS,
)
from uwbd.config.zenoh_checks import endpoint_problem

__all__ = [
    "G_MPS2", "IMU_DRIVERS", "IMU_INTRINSIC_KEYS", "IMU_LIMIT_KEYS", "IMU_NOISE_KEYS",
    "MAX_CONFIG_BYTES", "MIN_ANCHOR_SPACING_M", "NOISE_PLAUSIBLE_FACTOR",
    "ROTATION_TOLERANCE", "STANDARD_BAUDS", "UWB_DRIVERS", "ZENOH_PROTOCOLS", "Config",
    "ConfigError", "SourceConfig", "Vec3", "apply_overrides", "default_robot_name",
    "endpoint_problem", "load", "parse", "to_toml",
]
