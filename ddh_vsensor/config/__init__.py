"""Machine configuration: the YAML file (:mod:`.load`), validated (:mod:`.validate`) into the
frozen dataclasses of :mod:`.schema`."""

from ddh_vsensor.config.errors import ConfigError, UnknownUnitError
from ddh_vsensor.config.load import load_config, parse_yaml
from ddh_vsensor.config.schema import (DEFAULT_CONFIG, OilConfig, HydraulicsConfig, PumpConfig, LoadConfig, MotorConfig, UnitConfig, TablesConfig, EstimatorConfig, DEFAULT_BUS, HALL_BITS_MAX, UNITS_MAX, CanUnitConfig, CanConfig, END_STOP_OVERTRAVEL_MAX_MM, WORK_SPEED_LEVELS, CycleStepConfig, CycleConfig, WorkUnitConfig, WorkCycleConfig, RESERVED_CYCLE_NAMES, PresetMode, FaultsConfig, HealthConfig, TolerancesConfig, DATASHEET_TOLERANCES, Config)
from ddh_vsensor.config.validate import parse_config

__all__ = ['CanConfig', 'CanUnitConfig', 'Config', 'ConfigError', 'CycleConfig', 'CycleStepConfig', 'DEFAULT_BUS', 'DEFAULT_CONFIG', 'END_STOP_OVERTRAVEL_MAX_MM', 'EstimatorConfig', 'DATASHEET_TOLERANCES', 'FaultsConfig', 'HealthConfig', 'HALL_BITS_MAX', 'HydraulicsConfig', 'LoadConfig', 'MotorConfig', 'OilConfig', 'PresetMode', 'PumpConfig', 'RESERVED_CYCLE_NAMES', 'TablesConfig', 'TolerancesConfig', 'UNITS_MAX', 'UnitConfig', 'UnknownUnitError', 'WORK_SPEED_LEVELS', 'WorkCycleConfig', 'WorkUnitConfig', 'load_config', 'parse_config', 'parse_yaml']
