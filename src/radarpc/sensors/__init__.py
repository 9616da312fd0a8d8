"""Sensor configs: the RADIal-like DDMA radar (:mod:`radarpc.sensors.radial`) and the
ColoRadar radars (:mod:`radarpc.sensors.coloradar`)."""
from radarpc.sensors.radial import (  # noqa: F401
    RADIAL,
    RADIAL_S,
    RADIAL_SENSORS,
    TINY,
    Calibration,
    DDMARadarConfig,
    channel_errors,
    load_calibration,
    make_calibration,
    radial_sensor,
    save_calibration,
    steering_vectors,
)
from radarpc.sensors.coloradar import AWR1843, CASCADE, AWR1843_FOV, ColoRadarCalib, ColoRadarChipConfig, RadarFOV, Transform, load_calib, write_calib  # noqa: F401
