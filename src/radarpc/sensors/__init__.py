"""Sensor dataclasses and presets: the RADIal-like DDMA radar (:mod:`radarpc.sensors.radial`) and
the ColoRadar radars (:mod:`radarpc.sensors.coloradar`).

Reading and writing calibration files is in :mod:`radarpc.data.radial_format` and
:mod:`radarpc.data.coloradar_format`; a simulated unit's calibration is synthesized by
:func:`radarpc.sim.radial_calibration.make_calibration`.
"""
from radarpc.sensors.coloradar import (  # noqa: F401
    AWR1843,
    AWR1843_FOV,
    CASCADE,
    DEFAULT_CALIB,
    ColoRadarCalib,
    ColoRadarChipConfig,
    RadarFOV,
    Transform,
)
from radarpc.sensors.radial import (  # noqa: F401
    RADIAL,
    RADIAL_S,
    RADIAL_SENSORS,
    TINY,
    Calibration,
    DDMARadarConfig,
    radial_sensor,
)
